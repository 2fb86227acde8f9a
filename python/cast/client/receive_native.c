/* A shared-memory session's socket read, its frames cut and handed on, in C (the compiled build only).
 *
 * A Python watcher on the server's host gets its events as EVENTS frames on
 * its session's Unix socket, read by its dispatcher thread. The pure path from
 * the dispatcher's poll to the watch's decoder (ClientSession.poll,
 * _read_available, Inbox.receive, FrameReader.feed, _handle, the handler,
 * WatchStream._frame, _turn_frames, turn_events, _stop_reading) is a dozen
 * Python functions per frame, 35-80 us on the cold caches a 30 Hz watcher
 * meets (docs/performance-m8.md, "The Python watcher's own path, step by
 * step"). This module does the same with the CPython API only:
 *
 * - Receiver(sock, chunk): what ClientSession._read_available does with its
 *   Inbox and FrameReader: reads of up to `chunk` bytes until the socket is
 *   empty, frames cut with the descriptors they carry, the same bounds and
 *   the same errors (the session ended with the same reason), each frame
 *   handed on in order: an EVENTS frame to the handler registered for its
 *   call (session.event_handlers), any other to session._handle(Frame).
 *   pump(session) is ClientSession.poll() without a wait: the read lock
 *   tried, the socket read, the lock let go and what the pure
 *   _stop_reading does done when there is something to do (it calls
 *   session._after_reading()).
 * - DirectTurn(...): a watch call's handler. On the dispatcher thread, with
 *   no frame of the call queued or being turned, it turns the frame at once
 *   (the C decoder, cast.client._events_native.turn), as WatchStream._frame
 *   followed by _turn_frames would; in every other case it calls
 *   WatchStream._frame, the pure path.
 *
 * tests/client/test_native_receive.py holds both paths to the same frames,
 * events, errors and ends.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>
#include <errno.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

/* Frame kinds and bounds of cast.wire.shared_memory. */
enum { WRITES = 4, WELCOME = 10, SEGMENT = 12, REPLIES = 14, EVENTS = 15 };
enum { MAX_FDS_PER_READ = 16 };
#define MAX_FRAME (1u << 16)
#define MAX_WRITES_FRAME (64u << 20)

static int large(unsigned kind) { return kind == WRITES || kind == REPLIES || kind == EVENTS; }
static int with_fd(unsigned kind) { return kind == WELCOME || kind == SEGMENT; }

/* What configure() was given: cast.wire.shared_memory's Frame and ProtocolError, cast.errors.CastError. */
static PyObject *frame_cls, *protocol_error, *cast_error;

static PyObject *s_dead, *s_end, *s_handle, *s_event_handlers, *s_read_lock, *s_acquire, *s_release, *s_fileno,
    *s_writes, *s_followers, *s_retired, *s_answered, *s_after_reading, *s_read, *s_socket_broke, *s_turning,
    *s_turn_frames, *s_turn_failed;

/* ------------------------------------------------------------- Receiver */

typedef struct {
    int fd;
    uint32_t kind;
    Py_ssize_t start, length; /* the body (after the kind byte) in the buffer */
} Cut;

typedef struct {
    PyObject_HEAD
    PyObject *sock;
    Py_ssize_t chunk;
    uint8_t *buf;
    Py_ssize_t len, cap;
    int *fds; /* descriptors come, not yet given to a frame, oldest first */
    Py_ssize_t nfds, fds_cap;
    Cut *cuts;
    Py_ssize_t cuts_cap;
    int busy;
    unsigned long long reads; /* recvmsg calls made, for the tests that count them */
} Receiver;

/* session.<name> is true: 1, 0, or -1 with the error set. */
static int attr_true(PyObject *obj, PyObject *name) {
    PyObject *v = PyObject_GetAttr(obj, name);
    if (v == NULL) return -1;
    int t = PyObject_IsTrue(v);
    Py_DECREF(v);
    return t;
}

/* session._end(why), keeping no error of its own from the caller's. */
static int end_session(PyObject *session, PyObject *why) {
    if (why == NULL) return -1;
    PyObject *done = PyObject_CallMethodOneArg(session, s_end, why);
    Py_DECREF(why);
    if (done == NULL) return -1;
    Py_DECREF(done);
    return 0;
}

/* session._end(prefix + str(the error set now)): a read's OSError or ProtocolError ("read failed: ..."), or a
 * frame's ProtocolError (no prefix), in the words the pure path uses. */
static int end_with_error(PyObject *session, const char *prefix) {
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyErr_NormalizeException(&type, &value, &tb);
    PyObject *why = value != NULL ? PyUnicode_FromFormat("%s%S", prefix, value) : NULL;
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(tb);
    return end_session(session, why);
}

static int ensure_room(Receiver *self, Py_ssize_t room) {
    if (self->cap - self->len >= room) return 0;
    Py_ssize_t want = self->len + room;
    uint8_t *grown = PyMem_Realloc(self->buf, (size_t)want);
    if (grown == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    self->buf = grown;
    self->cap = want;
    return 0;
}

static int push_fds(Receiver *self, const int *fds, Py_ssize_t n) {
    if (self->nfds + n > self->fds_cap) {
        Py_ssize_t want = (self->nfds + n) * 2;
        int *grown = PyMem_Realloc(self->fds, (size_t)want * sizeof(int));
        if (grown == NULL) {
            for (Py_ssize_t i = 0; i < n; i++) close(fds[i]);
            PyErr_NoMemory();
            return -1;
        }
        self->fds = grown;
        self->fds_cap = want;
    }
    memcpy(self->fds + self->nfds, fds, (size_t)n * sizeof(int));
    self->nfds += n;
    return 0;
}

/* The ProtocolError of a frame that breaks the protocol, with the pure FrameReader's words. */
static void refuse_frame(uint32_t length, int kind_known, unsigned kind, int fd_missing) {
    if (fd_missing) {
        PyErr_Format(protocol_error, "frame of kind %u came without its memory file", kind);
    } else if (!kind_known) {
        PyErr_Format(protocol_error, "frame of %u bytes (1 to %u allowed)", length, MAX_WRITES_FRAME);
    } else if (large(kind)) {
        PyErr_Format(protocol_error,
                     "frame of kind %u has %u bytes (1 to %u allowed: a write request over 64 MiB does not fit the "
                     "Write stream either; stage large values)",
                     kind, length, MAX_WRITES_FRAME);
    } else {
        PyErr_Format(protocol_error, "frame of kind %u has %u bytes (1 to %u allowed)", kind, length, MAX_FRAME);
    }
}

/* The complete frames in the buffer, into self->cuts: their number, the bytes they take (*used) and the
 * descriptors they take (*taken), or -1 with a ProtocolError set (nothing taken). */
static Py_ssize_t cut(Receiver *self, Py_ssize_t *used, Py_ssize_t *taken) {
    Py_ssize_t at = 0, n = 0, fds = 0;
    while (self->len - at >= 4) {
        uint32_t length;
        memcpy(&length, self->buf + at, 4); /* little-endian, as the whole protocol */
        if (length < 1 || length > MAX_WRITES_FRAME) {
            refuse_frame(length, 0, 0, 0);
            return -1;
        }
        if (self->len - at < 5) break; /* the kind decides the bound */
        unsigned kind = self->buf[at + 4];
        if (length > (large(kind) ? MAX_WRITES_FRAME : MAX_FRAME)) {
            refuse_frame(length, 1, kind, 0);
            return -1;
        }
        if (self->len - at - 4 < (Py_ssize_t)length) break;
        int fd = -1;
        if (with_fd(kind)) {
            if (fds == self->nfds) {
                refuse_frame(length, 1, kind, 1);
                return -1;
            }
            fd = self->fds[fds++];
        }
        if (n == self->cuts_cap) {
            Py_ssize_t want = n ? n * 2 : 8;
            Cut *grown = PyMem_Realloc(self->cuts, (size_t)want * sizeof(Cut));
            if (grown == NULL) {
                PyErr_NoMemory();
                return -1;
            }
            self->cuts = grown;
            self->cuts_cap = want;
        }
        self->cuts[n++] = (Cut){fd, kind, at + 5, (Py_ssize_t)length - 1};
        at += 4 + length;
    }
    *used = at;
    *taken = fds;
    return n;
}

/* One frame handed on: an EVENTS frame to its call's handler (if any), any other to session._handle. */
static int hand_on(PyObject *session, const uint8_t *body, Cut *c) {
    if (c->kind == EVENTS) {
        uint64_t call = 0;
        Py_ssize_t head = c->length < 8 ? c->length : 8;
        for (Py_ssize_t i = head - 1; i >= 0; i--) call = call << 8 | body[i];
        PyObject *handlers = PyObject_GetAttr(session, s_event_handlers);
        if (handlers == NULL) return -1;
        PyObject *key = PyLong_FromUnsignedLongLong(call);
        PyObject *handler = key != NULL ? PyObject_GetItem(handlers, key) : NULL;
        Py_XDECREF(key);
        Py_DECREF(handlers);
        if (handler == NULL) {
            if (!PyErr_ExceptionMatches(PyExc_KeyError)) return -1;
            PyErr_Clear(); /* a call that ended: its frames go */
            return 0;
        }
        PyObject *events = PyBytes_FromStringAndSize((const char *)body + head, c->length - head);
        PyObject *done = events != NULL ? PyObject_CallOneArg(handler, events) : NULL;
        Py_XDECREF(events);
        Py_DECREF(handler);
        if (done == NULL) return -1;
        Py_DECREF(done);
        return 0;
    }
    PyObject *fd = NULL;
    if (c->fd >= 0) {
        fd = PyLong_FromLong(c->fd);
        if (fd == NULL) return -1;
        c->fd = -1; /* the frame's now, whatever happens */
    } else {
        fd = Py_None;
        Py_INCREF(fd);
    }
    PyObject *kind = PyLong_FromUnsignedLong(c->kind);
    PyObject *data = PyBytes_FromStringAndSize((const char *)body, c->length);
    PyObject *frame = kind != NULL && data != NULL ? PyObject_CallFunctionObjArgs(frame_cls, kind, data, fd, NULL)
                                                   : NULL;
    Py_XDECREF(kind);
    Py_XDECREF(data);
    Py_DECREF(fd);
    if (frame == NULL) return -1;
    PyObject *done = PyObject_CallMethodOneArg(session, s_handle, frame);
    Py_DECREF(frame);
    if (done == NULL) return -1;
    Py_DECREF(done);
    return 0;
}

/* ClientSession._read_available: read and hand on every frame the socket holds now (the read lock held). */
static int read_available(Receiver *self, PyObject *session) {
    for (;;) {
        int dead = attr_true(session, s_dead);
        if (dead != 0) return dead < 0 ? -1 : 0;
        if (ensure_room(self, self->chunk) < 0) return -1;
        PyObject *fileno = PyObject_CallMethodNoArgs(self->sock, s_fileno);
        if (fileno == NULL) return -1;
        long fd = PyLong_AsLong(fileno);
        Py_DECREF(fileno);
        if (fd == -1 && PyErr_Occurred()) return -1;
        union {
            char buf[CMSG_SPACE(MAX_FDS_PER_READ * sizeof(int))];
            struct cmsghdr align;
        } control;
        struct iovec iov = {self->buf + self->len, (size_t)self->chunk};
        struct msghdr msg = {0};
        msg.msg_iov = &iov;
        msg.msg_iovlen = 1;
        msg.msg_control = control.buf;
        msg.msg_controllen = sizeof control.buf;
        ssize_t count = recvmsg((int)fd, &msg, MSG_DONTWAIT | MSG_CMSG_CLOEXEC);
        self->reads++;
        if (count < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) return 0;
            PyErr_SetFromErrno(PyExc_OSError);
            return end_with_error(session, "read failed: ");
        }
        int got[MAX_FDS_PER_READ];
        Py_ssize_t ngot = 0;
        for (struct cmsghdr *h = CMSG_FIRSTHDR(&msg); h != NULL; h = CMSG_NXTHDR(&msg, h)) {
            if (h->cmsg_level != SOL_SOCKET || h->cmsg_type != SCM_RIGHTS) continue;
            Py_ssize_t n = (Py_ssize_t)((h->cmsg_len - CMSG_LEN(0)) / sizeof(int));
            for (Py_ssize_t i = 0; i < n && ngot < MAX_FDS_PER_READ; i++) {
                memcpy(&got[ngot++], CMSG_DATA(h) + i * sizeof(int), sizeof(int));
            }
        }
        if (msg.msg_flags & MSG_CTRUNC) {
            for (Py_ssize_t i = 0; i < ngot; i++) close(got[i]);
            PyErr_SetString(protocol_error, "more memory files arrived than one read takes");
            return end_with_error(session, "read failed: ");
        }
        if (push_fds(self, got, ngot) < 0) return -1;
        if (count == 0) {
            return end_session(session, PyUnicode_FromString("the server closed the session"));
        }
        int drained = count < self->chunk; /* the socket held no more: no second read to learn it */
        self->len += count;
        Py_ssize_t used = 0, taken = 0;
        Py_ssize_t n = cut(self, &used, &taken);
        if (n < 0) {
            if (!PyErr_ExceptionMatches(protocol_error)) return -1;
            return end_with_error(session, "");
        }
        /* The descriptors the frames took leave the queue before any is handed on (stray() may be asked). */
        memmove(self->fds, self->fds + taken, (size_t)(self->nfds - taken) * sizeof(int));
        self->nfds -= taken;
        /* The bodies are copied out as each frame is handed on; the handlers cannot read this receiver again
         * (the read lock is held), so the buffer stays as it is until all are. */
        int failed = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            Cut *c = &self->cuts[i];
            if (failed) {
                if (c->fd >= 0) close(c->fd); /* the frames after an error are lost (as the pure path's) */
                continue;
            }
            if (hand_on(session, self->buf + c->start, c) < 0) {
                failed = 1;
                if (c->fd >= 0) close(c->fd);
            }
        }
        memmove(self->buf, self->buf + used, (size_t)(self->len - used));
        self->len -= used;
        if (self->len == 0 && self->cap > 4 * self->chunk) { /* a large frame's room is not kept for good */
            PyMem_Free(self->buf);
            self->buf = NULL;
            self->cap = 0;
        }
        if (failed) {
            if (!PyErr_ExceptionMatches(protocol_error)) return -1;
            return end_with_error(session, "");
        }
        if (drained) return 0;
    }
}

static PyObject *receiver_read_available(Receiver *self, PyObject *session) {
    if (self->busy) {
        PyErr_SetString(PyExc_RuntimeError, "read_available() called again while it reads (hold the read lock)");
        return NULL;
    }
    self->busy = 1;
    int r = read_available(self, session);
    self->busy = 0;
    if (r < 0) return NULL;
    Py_RETURN_NONE;
}

/* What ClientSession._stop_reading does after letting the read lock go, when there is something to do. */
static int after_reading(PyObject *session) {
    PyObject *writes = PyObject_GetAttr(session, s_writes);
    if (writes == NULL) return -1;
    int todo = attr_true(writes, s_followers);
    if (todo == 0) todo = attr_true(session, s_retired);
    if (todo == 0) todo = attr_true(writes, s_answered);
    Py_DECREF(writes);
    if (todo <= 0) return todo;
    PyObject *done = PyObject_CallMethodNoArgs(session, s_after_reading);
    if (done == NULL) return -1;
    Py_DECREF(done);
    return 0;
}

static PyObject *receiver_pump(Receiver *self, PyObject *session) {
    int dead = attr_true(session, s_dead);
    if (dead != 0) {
        if (dead < 0) return NULL;
        Py_RETURN_TRUE;
    }
    PyObject *lock = PyObject_GetAttr(session, s_read_lock);
    if (lock == NULL) return NULL;
    PyObject *got = PyObject_CallMethodOneArg(lock, s_acquire, Py_False);
    int taken = got == NULL ? -1 : PyObject_IsTrue(got);
    Py_XDECREF(got);
    if (taken <= 0) {
        Py_DECREF(lock);
        if (taken < 0) return NULL;
        Py_RETURN_FALSE;
    }
    PyObject *read = receiver_read_available(self, session);
    /* As the pure path's finally: the lock goes and what was left for after the read is done, whatever came. */
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyObject *released = PyObject_CallMethodNoArgs(lock, s_release);
    Py_DECREF(lock);
    int after = released == NULL ? -1 : after_reading(session);
    Py_XDECREF(released);
    if (read == NULL) {
        if (after < 0) PyErr_Clear();
        PyErr_Restore(type, value, tb);
        return NULL;
    }
    Py_DECREF(read);
    if (after < 0) return NULL;
    Py_RETURN_TRUE;
}

static PyObject *receiver_stray(Receiver *self, PyObject *unused) {
    (void)unused;
    PyObject *out = PyList_New(self->nfds);
    if (out == NULL) return NULL;
    for (Py_ssize_t i = 0; i < self->nfds; i++) {
        PyObject *fd = PyLong_FromLong(self->fds[i]);
        if (fd == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, i, fd);
    }
    self->nfds = 0;
    return out;
}

static PyObject *receiver_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    PyObject *sock;
    Py_ssize_t chunk;
    static char *names[] = {"sock", "chunk", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "On:Receiver", names, &sock, &chunk)) return NULL;
    if (chunk < 1 || chunk > (Py_ssize_t)MAX_WRITES_FRAME) {
        PyErr_Format(PyExc_ValueError, "chunk is %zd bytes: give 1 to %u", chunk, MAX_WRITES_FRAME);
        return NULL;
    }
    if (frame_cls == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "call configure() before making a Receiver");
        return NULL;
    }
    Receiver *self = (Receiver *)type->tp_alloc(type, 0);
    if (self == NULL) return NULL;
    Py_INCREF(sock);
    self->sock = sock;
    self->chunk = chunk;
    return (PyObject *)self;
}

static int receiver_traverse(Receiver *self, visitproc visit, void *arg) {
    Py_VISIT(self->sock);
    return 0;
}

static int receiver_clear(Receiver *self) {
    Py_CLEAR(self->sock);
    return 0;
}

static void receiver_dealloc(Receiver *self) {
    PyObject_GC_UnTrack(self);
    receiver_clear(self);
    for (Py_ssize_t i = 0; i < self->nfds; i++) close(self->fds[i]); /* never handed to a frame */
    PyMem_Free(self->buf);
    PyMem_Free(self->fds);
    PyMem_Free(self->cuts);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMethodDef receiver_methods[] = {
    {"read_available", (PyCFunction)receiver_read_available, METH_O,
     "read_available(session): read and hand on every frame the socket holds now (call with its read lock)."},
    {"pump", (PyCFunction)receiver_pump, METH_O,
     "pump(session) -> bool: ClientSession.poll() without a wait; False when another thread reads."},
    {"stray", (PyCFunction)receiver_stray, METH_NOARGS, "stray() -> list[int]: descriptors no frame took (to close)."},
    {NULL, NULL, 0, NULL},
};

static PyMemberDef receiver_members[] = {
    {"reads", T_ULONGLONG, offsetof(Receiver, reads), READONLY, "How many reads of the socket it made."},
    {"capacity", T_PYSSIZET, offsetof(Receiver, cap), READONLY, "The bytes its buffer holds room for now."},
    {NULL, 0, 0, 0, NULL},
};

static PyTypeObject ReceiverType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "cast.client._receive_native.Receiver",
    .tp_basicsize = sizeof(Receiver),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "Receiver(sock, chunk): a session socket's reads, cut into frames and handed on (read_available).",
    .tp_new = receiver_new,
    .tp_traverse = (traverseproc)receiver_traverse,
    .tp_clear = (inquiry)receiver_clear,
    .tp_dealloc = (destructor)receiver_dealloc,
    .tp_methods = receiver_methods,
    .tp_members = receiver_members,
};

/* ------------------------------------------------------------ DirectTurn */

typedef struct {
    PyObject_HEAD
    PyObject *stream, *read, *lock, *frames, *claim, *sink, *seen, *turn, *slow_turn, *fallback;
    unsigned long ident;
    vectorcallfunc vectorcall;
} DirectTurn;

/* Whether the frame may be turned here and now: the call current, not broken, nothing queued or turning. */
static int may_turn(DirectTurn *self) {
    PyObject *read = PyObject_GetAttr(self->stream, s_read);
    if (read == NULL) return -1;
    int current = read == self->read;
    Py_DECREF(read);
    if (!current) return 0;
    int broke = attr_true(self->stream, s_socket_broke);
    if (broke != 0) return broke < 0 ? -1 : 0;
    Py_ssize_t queued = PyObject_Length(self->frames);
    if (queued != 0) return queued < 0 ? -1 : 0;
    int turning = attr_true(self->stream, s_turning);
    return turning < 0 ? -1 : !turning;
}

/* The frame turned: the C decoder, or the pure path where it declines; a CastError ends the call there. */
static int turn_now(DirectTurn *self, PyObject *body) {
    PyObject *args[4] = {body, self->claim, self->sink, self->seen};
    PyObject *done = PyObject_Vectorcall(self->turn, args, 4, NULL);
    if (done == Py_False) { /* what only protobuf decodes */
        Py_DECREF(done);
        PyObject *slow_args[4] = {body, self->read, self->sink, self->seen};
        done = PyObject_Vectorcall(self->slow_turn, slow_args, 4, NULL);
    }
    if (done != NULL) {
        Py_DECREF(done);
        return 0;
    }
    if (!PyErr_ExceptionMatches(cast_error)) return -1;
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyErr_NormalizeException(&type, &value, &tb);
    PyObject *failed = value != NULL ? PyObject_CallMethodOneArg(self->stream, s_turn_failed, value) : NULL;
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(tb);
    if (failed == NULL) return -1;
    Py_DECREF(failed);
    return 0;
}

static PyObject *direct_call(DirectTurn *self, PyObject *const *args, size_t nargsf, PyObject *kwnames) {
    if (PyVectorcall_NARGS(nargsf) != 1 || kwnames != NULL) {
        PyErr_SetString(PyExc_TypeError, "a watch call's handler takes the frame's events (1 positional argument)");
        return NULL;
    }
    if (PyThread_get_thread_ident() != self->ident) return PyObject_CallOneArg(self->fallback, args[0]);
    PyObject *got = PyObject_CallMethodNoArgs(self->lock, s_acquire);
    if (got == NULL) return NULL;
    Py_DECREF(got);
    int ok = may_turn(self), result = -1;
    if (ok == 0) {
        result = 0;
    } else if (ok > 0 && PyObject_SetAttr(self->stream, s_turning, Py_True) == 0) {
        result = turn_now(self, args[0]);
        PyObject *type, *value, *tb;
        PyErr_Fetch(&type, &value, &tb);
        if (PyObject_SetAttr(self->stream, s_turning, Py_False) < 0) {
            result = -1;
            Py_XDECREF(type);
            Py_XDECREF(value);
            Py_XDECREF(tb);
        } else {
            PyErr_Restore(type, value, tb);
        }
        if (result == 0 && PyObject_Length(self->frames) > 0) {
            /* Frames a claim read from the socket meanwhile (queued, as _frame does while turning): in order. */
            PyObject *more = PyObject_CallMethodNoArgs(self->stream, s_turn_frames);
            if (more == NULL) result = -1;
            Py_XDECREF(more);
        }
        if (result == 0 && PyErr_Occurred()) result = -1;
        ok = 1;
    }
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyObject *released = PyObject_CallMethodNoArgs(self->lock, s_release);
    if (released == NULL) {
        Py_XDECREF(type);
        Py_XDECREF(value);
        Py_XDECREF(tb);
        return NULL;
    }
    Py_DECREF(released);
    PyErr_Restore(type, value, tb);
    if (result < 0) return NULL;
    if (ok == 0) return PyObject_CallOneArg(self->fallback, args[0]); /* the pure path decides, in order */
    Py_RETURN_NONE;
}

static PyObject *direct_vectorcall(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames) {
    return direct_call((DirectTurn *)self, args, nargsf, kwnames);
}

static PyObject *direct_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    PyObject *stream, *read, *lock, *frames, *claim, *sink, *seen, *turn, *slow_turn, *fallback;
    unsigned long ident;
    static char *names[] = {"stream", "read", "lock", "frames", "claim", "sink", "seen", "turn", "slow_turn",
                            "fallback", "ident", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OOOOOOO!OOOk:DirectTurn", names, &stream, &read, &lock, &frames,
                                     &claim, &sink, &PyDict_Type, &seen, &turn, &slow_turn, &fallback, &ident)) {
        return NULL;
    }
    if (cast_error == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "call configure() before making a DirectTurn");
        return NULL;
    }
    DirectTurn *self = (DirectTurn *)type->tp_alloc(type, 0);
    if (self == NULL) return NULL;
    PyObject **slots[] = {&self->stream, &self->read, &self->lock, &self->frames, &self->claim, &self->sink,
                          &self->seen, &self->turn, &self->slow_turn, &self->fallback};
    PyObject *given[] = {stream, read, lock, frames, claim, sink, seen, turn, slow_turn, fallback};
    for (size_t i = 0; i < sizeof given / sizeof given[0]; i++) {
        Py_INCREF(given[i]);
        *slots[i] = given[i];
    }
    self->ident = ident;
    self->vectorcall = direct_vectorcall;
    return (PyObject *)self;
}

static int direct_traverse(DirectTurn *self, visitproc visit, void *arg) {
    Py_VISIT(self->stream);
    Py_VISIT(self->read);
    Py_VISIT(self->lock);
    Py_VISIT(self->frames);
    Py_VISIT(self->claim);
    Py_VISIT(self->sink);
    Py_VISIT(self->seen);
    Py_VISIT(self->turn);
    Py_VISIT(self->slow_turn);
    Py_VISIT(self->fallback);
    return 0;
}

static int direct_clear(DirectTurn *self) {
    Py_CLEAR(self->stream);
    Py_CLEAR(self->read);
    Py_CLEAR(self->lock);
    Py_CLEAR(self->frames);
    Py_CLEAR(self->claim);
    Py_CLEAR(self->sink);
    Py_CLEAR(self->seen);
    Py_CLEAR(self->turn);
    Py_CLEAR(self->slow_turn);
    Py_CLEAR(self->fallback);
    return 0;
}

static void direct_dealloc(DirectTurn *self) {
    PyObject_GC_UnTrack(self);
    direct_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyTypeObject DirectTurnType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "cast.client._receive_native.DirectTurn",
    .tp_basicsize = sizeof(DirectTurn),
    .tp_vectorcall_offset = offsetof(DirectTurn, vectorcall),
    .tp_call = PyVectorcall_Call,
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_doc = "DirectTurn(stream, read, lock, frames, claim, sink, seen, turn, slow_turn, fallback, ident): a watch\n"
              "call's EVENTS handler that turns a frame at once on the dispatcher thread (else calls fallback).",
    .tp_new = direct_new,
    .tp_traverse = (traverseproc)direct_traverse,
    .tp_clear = (inquiry)direct_clear,
    .tp_dealloc = (destructor)direct_dealloc,
};

/* ----------------------------------------------------------------- module */

PyDoc_STRVAR(configure_doc,
"configure(frame_cls, protocol_error, cast_error)\n\n"
"cast.wire.shared_memory's Frame and ProtocolError, and cast.errors.CastError (what ends a turned call).");

static PyObject *configure(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *frame, *protocol, *error;
    if (!PyArg_ParseTuple(args, "OOO", &frame, &protocol, &error)) return NULL;
    if (!PyType_Check(protocol) || !PyType_IsSubtype((PyTypeObject *)protocol, (PyTypeObject *)PyExc_Exception)
        || !PyType_Check(error) || !PyType_IsSubtype((PyTypeObject *)error, (PyTypeObject *)PyExc_Exception)) {
        PyErr_SetString(PyExc_TypeError, "protocol_error and cast_error must be exception classes");
        return NULL;
    }
    Py_INCREF(frame);
    Py_INCREF(protocol);
    Py_INCREF(error);
    Py_XSETREF(frame_cls, frame);
    Py_XSETREF(protocol_error, protocol);
    Py_XSETREF(cast_error, error);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"configure", configure, METH_VARARGS, configure_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "cast.client._receive_native",
    "A shared-memory session's socket read and its frames handed on in C (cast.client.shm_session and\n"
    "cast.client.watch_stream use it).", -1, methods, NULL, NULL, NULL, NULL,
};

#define INTERN(var, text) \
    if ((var = PyUnicode_InternFromString(text)) == NULL) return NULL

PyMODINIT_FUNC PyInit__receive_native(void) {
    INTERN(s_dead, "dead");
    INTERN(s_end, "_end");
    INTERN(s_handle, "_handle");
    INTERN(s_event_handlers, "event_handlers");
    INTERN(s_read_lock, "_read_lock");
    INTERN(s_acquire, "acquire");
    INTERN(s_release, "release");
    INTERN(s_fileno, "fileno");
    INTERN(s_writes, "writes");
    INTERN(s_followers, "followers");
    INTERN(s_retired, "_retired");
    INTERN(s_answered, "answered");
    INTERN(s_after_reading, "_after_reading");
    INTERN(s_read, "_read");
    INTERN(s_socket_broke, "_socket_broke");
    INTERN(s_turning, "_turning");
    INTERN(s_turn_frames, "_turn_frames");
    INTERN(s_turn_failed, "_turn_failed");
    if (PyType_Ready(&ReceiverType) < 0 || PyType_Ready(&DirectTurnType) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    if (PyModule_AddObjectRef(m, "Receiver", (PyObject *)&ReceiverType) < 0
        || PyModule_AddObjectRef(m, "DirectTurn", (PyObject *)&DirectTurnType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
