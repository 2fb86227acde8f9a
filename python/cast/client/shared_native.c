/* Values lent by shared memory claimed, read in place and given back, in C (the compiled build only).
 *
 * A watcher on the server's host is lent each large value in place
 * (docs/client-protocol.md): claiming it (ReadCall.claim_at, then
 * ClientSession.claim_at) makes a read-only view of the segment it is in and a
 * Lease, and the lease's end gives it back (Lease.__del__, give_back, _flush,
 * _write, _sent): eight Python functions per value, which on the cold caches
 * of a 30 Hz watcher cost more than the C++ client's whole receive path
 * (docs/performance-m8.md, "Claims and leases in C"). This module does the
 * same with the CPython API only:
 *
 * - Lease(session, value_id): its end sends RELEASE at once when nothing else
 *   waits to be sent and no other thread is sending (the send lock free, the
 *   whole 13-byte frame taken by the socket); otherwise it hands the id to
 *   session.give_back, the pure path, which queues it for the thread sending.
 * - Claimer(read): called as claim(segment, offset, size, value_id) ->
 *   (view, lease), the same as ReadCall.claim_at for a segment the session
 *   has mapped and a place inside it. Everything else (the segment not yet
 *   come, a place past its end, the 64th reference of a call, when RECEIVED
 *   goes out) is left to ReadCall.claim_at, which answers as it always did.
 * - field_of(data, number): the bytes of a serialised message's top-level
 *   field as ValueView.field reads them (cast.client.views.field_of), or None
 *   for what it leaves to that function: anything refused (it says why), a
 *   number or a varint past 64 bits.
 * - timerfd_arm(fd, ns): the dispatcher's standby alarm armed and disarmed
 *   (cast.client.alarm), one system call without ctypes.
 *
 * tests/client/test_native_shared.py holds both paths to the same views,
 * counts, frames, fields and errors.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stddef.h>
#include <stdint.h>
#include <limits.h>
#include <string.h>
#include <sys/timerfd.h>
#include <time.h>

enum { RELEASE = 2, RECEIVED_EVERY = 64 };

/* Interned attribute and method names. */
static PyObject *s_dead, *s_unsent, *s_held_writes, *s_send_lock, *s_sock, *s_acquire, *s_release, *s_send,
    *s_give_back, *s_write, *s_send_waiting, *s_session, *s_count, *s_segments, *s_size, *s_view, *s_claim_at;

/* ------------------------------------------------------------------ Lease */

typedef struct {
    PyObject_HEAD
    PyObject *session;
    unsigned long long value_id;
} Lease;

/* The length of a deque (or any sized object) held in session.<name>; -1 with the error set. */
static Py_ssize_t waiting(PyObject *session, PyObject *name) {
    PyObject *q = PyObject_GetAttr(session, name);
    if (q == NULL) return -1;
    Py_ssize_t n = PyObject_Length(q);
    Py_DECREF(q);
    return n;
}

/* 1 when ids given back or write requests held back wait to be sent (session._unsent, held_writes), 0 when
 * none, -1 with the error set. */
static int others_waiting(PyObject *session) {
    Py_ssize_t unsent = waiting(session, s_unsent);
    if (unsent != 0) return unsent < 0 ? -1 : 1;
    Py_ssize_t held = waiting(session, s_held_writes);
    return held < 0 ? -1 : held > 0;
}

/* 1 when the frame was sent whole on the socket, 0 when the pure path must finish it (``rest`` then holds
 * what is left to send, a new reference), -1 with an error that is not the socket's. Call with the send lock. */
static int send_now(PyObject *session, PyObject *frame, PyObject **rest) {
    *rest = NULL;
    PyObject *sock = PyObject_GetAttr(session, s_sock);
    if (sock == NULL) return -1;
    PyObject *n = PyObject_CallMethodOneArg(sock, s_send, frame);
    Py_DECREF(sock);
    if (n == NULL) {
        if (!PyErr_ExceptionMatches(PyExc_OSError)) return -1;
        PyErr_Clear(); /* a full socket or a broken one: session._write waits for room or ends the session */
        Py_INCREF(frame);
        *rest = frame;
        return 0;
    }
    Py_ssize_t sent = PyLong_AsSsize_t(n);
    Py_DECREF(n);
    if (sent < 0) return PyErr_Occurred() ? -1 : 0;
    if (sent >= PyBytes_GET_SIZE(frame)) return 1;
    *rest = PyBytes_FromStringAndSize(PyBytes_AS_STRING(frame) + sent, PyBytes_GET_SIZE(frame) - sent);
    return *rest == NULL ? -1 : 0;
}

/* The fast RELEASE of one value: 1 done, 0 not tried (the pure path must give it back), -1 error. */
static int release_now(PyObject *session, unsigned long long value_id) {
    PyObject *dead = PyObject_GetAttr(session, s_dead);
    if (dead == NULL) return -1;
    int is_dead = PyObject_IsTrue(dead);
    Py_DECREF(dead);
    if (is_dead != 0) return is_dead < 0 ? -1 : 0;
    int others = others_waiting(session);
    if (others != 0) return others < 0 ? -1 : 0; /* they go first, in order: the pure path sends them with this id */
    PyObject *lock = PyObject_GetAttr(session, s_send_lock);
    if (lock == NULL) return -1;
    PyObject *got = PyObject_CallMethodOneArg(lock, s_acquire, Py_False);
    int taken = got == NULL ? -1 : PyObject_IsTrue(got);
    Py_XDECREF(got);
    if (taken <= 0) {
        Py_DECREF(lock);
        return taken; /* another thread sends: the pure path queues the id for it */
    }
    unsigned char buf[13];
    uint32_t length = 9;
    memcpy(buf, &length, 4); /* little-endian, as the whole protocol (x86-64 and arm64 Linux) */
    buf[4] = RELEASE;
    memcpy(buf + 5, &value_id, 8);
    PyObject *frame = PyBytes_FromStringAndSize((const char *)buf, sizeof buf), *rest = NULL;
    int sent = frame == NULL ? -1 : send_now(session, frame, &rest);
    Py_XDECREF(frame);
    int result = sent < 0 ? -1 : 1;
    if (sent == 0) { /* what the socket did not take: the pure path waits for room, or ends the session */
        PyObject *done = PyObject_CallMethodOneArg(session, s_write, rest);
        if (done == NULL) result = -1;
        Py_XDECREF(done);
    }
    Py_XDECREF(rest);
    /* As ClientSession._sent: let the lock go, then send what others gave back meanwhile. */
    PyObject *et, *ev, *tb;
    PyErr_Fetch(&et, &ev, &tb);
    PyObject *let = PyObject_CallMethodNoArgs(lock, s_release);
    Py_DECREF(lock);
    if (let == NULL) {
        Py_XDECREF(et);
        Py_XDECREF(ev);
        Py_XDECREF(tb);
        return -1;
    }
    Py_DECREF(let);
    PyErr_Restore(et, ev, tb);
    if (result < 0) return -1;
    others = others_waiting(session);
    if (others < 0) return -1;
    if (others) {
        PyObject *more = PyObject_CallMethodNoArgs(session, s_send_waiting);
        if (more == NULL) return -1;
        Py_DECREF(more);
    }
    return 1;
}

static void lease_dealloc(Lease *self) {
    /* Freed wherever the last holder let go, maybe while an exception is being raised: keep it. */
    PyObject *et, *ev, *tb;
    PyErr_Fetch(&et, &ev, &tb);
    if (self->session != NULL) {
        int done = release_now(self->session, self->value_id);
        if (done == 0) {
            PyObject *id = PyLong_FromUnsignedLongLong(self->value_id);
            PyObject *r = id == NULL ? NULL : PyObject_CallMethodOneArg(self->session, s_give_back, id);
            Py_XDECREF(id);
            done = r == NULL ? -1 : 1;
            Py_XDECREF(r);
        }
        if (done < 0) PyErr_WriteUnraisable(self->session);
    }
    PyErr_Restore(et, ev, tb);
    Py_CLEAR(self->session);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *make_lease(PyTypeObject *type, PyObject *session, unsigned long long value_id) {
    Lease *self = (Lease *)type->tp_alloc(type, 0);
    if (self == NULL) return NULL;
    Py_INCREF(session);
    self->session = session;
    self->value_id = value_id;
    return (PyObject *)self;
}

static PyObject *lease_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    PyObject *session, *id;
    static char *names[] = {"session", "value_id", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OO!:Lease", names, &session, &PyLong_Type, &id)) return NULL;
    unsigned long long value_id = PyLong_AsUnsignedLongLong(id); /* a u64, as RELEASE carries it */
    if (value_id == (unsigned long long)-1 && PyErr_Occurred()) return NULL;
    return make_lease(type, session, value_id);
}

static PyObject *lease_get_session(Lease *self, void *closure) {
    (void)closure;
    PyObject *s = self->session != NULL ? self->session : Py_None;
    Py_INCREF(s);
    return s;
}

static PyObject *lease_get_value_id(Lease *self, void *closure) {
    (void)closure;
    return PyLong_FromUnsignedLongLong(self->value_id);
}

static PyGetSetDef lease_getset[] = {
    {"session", (getter)lease_get_session, NULL, "The session the value was lent on.", NULL},
    {"value_id", (getter)lease_get_value_id, NULL, "The value's id, which RELEASE names.", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject LeaseType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "cast.client._shared_native.Lease",
    .tp_doc = PyDoc_STR("Lease(session, value_id): a value the server lent, given back (RELEASE) once this "
                        "object is gone (records and views hold it)."),
    .tp_basicsize = sizeof(Lease),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = lease_new,
    .tp_dealloc = (destructor)lease_dealloc,
    .tp_getset = lease_getset,
};

/* ---------------------------------------------------------------- Claimer */

typedef struct {
    PyObject_HEAD
    PyObject *read; /* the ReadCall */
    vectorcallfunc vectorcall;
} Claimer;

/* ReadCall.claim_at(segment, offset, size, value_id): the pure path, for what the fast one does not do. */
static PyObject *claim_slowly(Claimer *self, PyObject *const *args) {
    PyObject *method = PyObject_GetAttr(self->read, s_claim_at);
    if (method == NULL) return NULL;
    PyObject *out = PyObject_Vectorcall(method, args, 4, NULL);
    Py_DECREF(method);
    return out;
}

static PyObject *claimer_call(Claimer *self, PyObject *const *args, size_t nargsf, PyObject *kwnames) {
    Py_ssize_t nargs = PyVectorcall_NARGS(nargsf);
    if (nargs != 4 || kwnames != NULL) {
        PyErr_SetString(PyExc_TypeError, "claim(segment, offset, size, value_id) takes 4 positional arguments");
        return NULL;
    }
    unsigned long long offset = PyLong_AsUnsignedLongLong(args[1]), size = PyLong_AsUnsignedLongLong(args[2]);
    unsigned long long value_id = PyLong_AsUnsignedLongLong(args[3]);
    if (PyErr_Occurred()) return NULL;
    PyObject *count = PyObject_GetAttr(self->read, s_count);
    if (count == NULL) return NULL;
    long long n = PyLong_AsLongLong(count);
    Py_DECREF(count);
    if (n == -1 && PyErr_Occurred()) return NULL;
    if ((n + 1) % RECEIVED_EVERY == 0) return claim_slowly(self, args); /* it sends RECEIVED */
    PyObject *session = PyObject_GetAttr(self->read, s_session);
    if (session == NULL) return NULL;
    PyObject *segments = PyObject_GetAttr(session, s_segments), *segment = NULL, *out = NULL;
    if (segments == NULL) goto done;
    segment = PyDict_Check(segments) ? PyDict_GetItemWithError(segments, args[0]) : NULL;
    if (segment == NULL) {
        if (!PyErr_Occurred()) out = claim_slowly(self, args); /* not come yet: it waits for its SEGMENT frame */
        goto done;
    }
    Py_INCREF(segment);
    PyObject *mapped = PyObject_GetAttr(segment, s_size);
    if (mapped == NULL) goto done;
    unsigned long long have = PyLong_AsUnsignedLongLong(mapped);
    Py_DECREF(mapped);
    if (have == (unsigned long long)-1 && PyErr_Occurred()) goto done;
    if (offset > have || size > have - offset) { /* the pure path says what is wrong */
        out = claim_slowly(self, args);
        goto done;
    }
    PyObject *now = PyLong_FromLongLong(n + 1);
    if (now == NULL) goto done;
    int set = PyObject_SetAttr(self->read, s_count, now);
    Py_DECREF(now);
    if (set < 0) goto done;
    /* The lease first, as ClientSession.claim_at: the value is given back whatever happens next. */
    PyObject *lease = make_lease(&LeaseType, session, value_id);
    if (lease == NULL) goto done;
    PyObject *view = PyObject_GetAttr(segment, s_view), *part = NULL;
    if (view != NULL) {
        part = PySequence_GetSlice(view, (Py_ssize_t)offset, (Py_ssize_t)(offset + size));
        Py_DECREF(view);
    }
    if (part != NULL) out = PyTuple_Pack(2, part, lease);
    Py_XDECREF(part);
    Py_DECREF(lease);
done:
    Py_XDECREF(segment);
    Py_XDECREF(segments);
    Py_DECREF(session);
    return out;
}

static PyObject *claimer_vectorcall(PyObject *self, PyObject *const *args, size_t nargsf, PyObject *kwnames) {
    return claimer_call((Claimer *)self, args, nargsf, kwnames);
}

static PyObject *claimer_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    PyObject *read;
    static char *names[] = {"read", NULL};
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "O:Claimer", names, &read)) return NULL;
    Claimer *self = (Claimer *)type->tp_alloc(type, 0);
    if (self == NULL) return NULL;
    Py_INCREF(read);
    self->read = read;
    self->vectorcall = claimer_vectorcall;
    return (PyObject *)self;
}

static int claimer_traverse(Claimer *self, visitproc visit, void *arg) {
    Py_VISIT(self->read);
    return 0;
}

static int claimer_clear(Claimer *self) {
    Py_CLEAR(self->read);
    return 0;
}

static void claimer_dealloc(Claimer *self) {
    PyObject_GC_UnTrack(self);
    claimer_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyTypeObject ClaimerType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "cast.client._shared_native.Claimer",
    .tp_doc = PyDoc_STR("Claimer(read): claim(segment, offset, size, value_id) -> (view, lease) on the read call "
                        "``read``, as ReadCall.claim_at."),
    .tp_basicsize = sizeof(Claimer),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_new = claimer_new,
    .tp_call = PyVectorcall_Call, /* a call with a tuple goes through the vectorcall too */
    .tp_vectorcall_offset = offsetof(Claimer, vectorcall),
    .tp_traverse = (traverseproc)claimer_traverse,
    .tp_clear = (inquiry)claimer_clear,
    .tp_dealloc = (destructor)claimer_dealloc,
};

/* --------------------------------------------------------------- field_of */

/* 0 and the value, or -1 for a varint that runs past the end or over 64 bits' worth of bytes (as views._varint). */
static int varint(const uint8_t **p, const uint8_t *end, uint64_t *out) {
    uint64_t v = 0;
    for (int shift = 0; shift <= 63; shift += 7) {
        if (*p >= end) return -1;
        uint8_t b = *(*p)++;
        if (shift == 63 && (b & 0x7e)) return -1; /* past 64 bits: Python's ints hold it, so it decides */
        v |= (uint64_t)(b & 0x7f) << shift;
        if (b < 0x80) {
            *out = v;
            return 0;
        }
    }
    return -1;
}

PyDoc_STRVAR(field_of_doc,
"field_of(data, number) -> memoryview | None\n\n"
"The bytes of top-level field ``number`` of the serialised message ``data`` (a memoryview), a slice of it,\n"
"the last occurrence winning and an absent field empty, as cast.client.views.field_of; None for what it\n"
"leaves to that function: whatever it refuses (it then says why), a number or a varint past 64 bits.");

static PyObject *field_of(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "field_of(data, number) takes 2 arguments");
        return NULL;
    }
    if (!PyMemoryView_Check(args[0])) Py_RETURN_NONE;
    long long number = PyLong_AsLongLong(args[1]);
    if (number == -1 && PyErr_Occurred()) { /* not an int of 64 bits: the pure path compares it as it is */
        PyErr_Clear();
        Py_RETURN_NONE;
    }
    Py_buffer *view = PyMemoryView_GET_BUFFER(args[0]);
    if (!PyBuffer_IsContiguous(view, 'C') || view->itemsize != 1) Py_RETURN_NONE;
    const uint8_t *start = (const uint8_t *)view->buf, *p = start, *end = start + view->len;
    Py_ssize_t from = 0, to = 0;
    while (p < end) {
        uint64_t key, n;
        if (varint(&p, end, &key) < 0) Py_RETURN_NONE;
        uint64_t tag = key >> 3;
        int kind = (int)(key & 7);
        if (kind == 2) {
            if (varint(&p, end, &n) < 0 || n > (uint64_t)(end - p)) Py_RETURN_NONE;
            if (tag == (uint64_t)number) {
                from = p - start;
                to = from + (Py_ssize_t)n;
            }
            p += n;
            continue;
        }
        if (tag == (uint64_t)number) Py_RETURN_NONE; /* a number, not bytes */
        if (kind == 0) {
            if (varint(&p, end, &n) < 0) Py_RETURN_NONE;
        } else if (kind == 1 || kind == 5) {
            if ((uint64_t)(end - p) < (kind == 1 ? 8u : 4u)) Py_RETURN_NONE;
            p += kind == 1 ? 8 : 4;
        } else {
            Py_RETURN_NONE;
        }
    }
    return PySequence_GetSlice(args[0], from, to);
}

/* ----------------------------------------------------------------- timerfd_arm */

PyDoc_STRVAR(timerfd_arm_doc,
    "timerfd_arm(fd, ns)\n--\n\n"
    "Arm the timerfd ``fd`` to expire once ``ns`` nanoseconds from now (0: disarm it); OSError as the system\n"
    "call fails. What cast.client.alarm.Alarm sets and cancels around every callback: ctypes' call into libc\n"
    "cost a 30 Hz watcher's cold caches about 11 us of each event's path (docs/performance-m8.md, \"The\n"
    "Python watcher's own path, step by step\").");

static PyObject *timerfd_arm(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "timerfd_arm takes 2 arguments (fd, ns), %zd given", nargs);
        return NULL;
    }
    int overflow = 0;
    long fd = PyLong_AsLongAndOverflow(args[0], &overflow);
    if (fd == -1 && PyErr_Occurred()) return NULL;
    long long ns = PyLong_AsLongLong(args[1]);
    if (ns == -1 && PyErr_Occurred()) return NULL;
    if (overflow || fd < 0 || fd > INT_MAX || ns < 0) {
        PyErr_Format(PyExc_ValueError, "timerfd_arm: fd must be a descriptor and ns 0 or more (fd %R, ns %R)",
                     args[0], args[1]);
        return NULL;
    }
    struct itimerspec spec;
    memset(&spec, 0, sizeof spec);
    spec.it_value.tv_sec = (time_t)(ns / 1000000000LL);
    spec.it_value.tv_nsec = (long)(ns % 1000000000LL);
    if (timerfd_settime((int)fd, 0, &spec, NULL) != 0) return PyErr_SetFromErrno(PyExc_OSError);
    Py_RETURN_NONE;
}

/* ----------------------------------------------------------------- module */

static PyMethodDef methods[] = {
    {"field_of", (PyCFunction)(void (*)(void))field_of, METH_FASTCALL, field_of_doc},
    {"timerfd_arm", (PyCFunction)(void (*)(void))timerfd_arm, METH_FASTCALL, timerfd_arm_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "cast.client._shared_native",
    "Values lent by shared memory claimed, read in place and given back, in C (cast.client.shm_session and\n"
    "cast.client.views use it); the dispatcher's alarm armed (cast.client.alarm).", -1, methods, NULL, NULL, NULL, NULL,
};

#define INTERN(var, text) \
    if ((var = PyUnicode_InternFromString(text)) == NULL) return NULL

PyMODINIT_FUNC PyInit__shared_native(void) {
    INTERN(s_dead, "dead");
    INTERN(s_unsent, "_unsent");
    INTERN(s_held_writes, "held_writes");
    INTERN(s_send_lock, "_send_lock");
    INTERN(s_sock, "_sock");
    INTERN(s_acquire, "acquire");
    INTERN(s_release, "release");
    INTERN(s_send, "send");
    INTERN(s_give_back, "give_back");
    INTERN(s_write, "_write");
    INTERN(s_send_waiting, "_send_waiting");
    INTERN(s_session, "session");
    INTERN(s_count, "count");
    INTERN(s_segments, "_segments");
    INTERN(s_size, "size");
    INTERN(s_view, "view");
    INTERN(s_claim_at, "claim_at");
    if (PyType_Ready(&LeaseType) < 0 || PyType_Ready(&ClaimerType) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    if (PyModule_AddObjectRef(m, "Lease", (PyObject *)&LeaseType) < 0
        || PyModule_AddObjectRef(m, "Claimer", (PyObject *)&ClaimerType) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
