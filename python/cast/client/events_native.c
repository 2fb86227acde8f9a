/* The Python client's EVENTS frames turned into change events in C (the compiled build only).
 *
 * An EVENTS frame on a shared-memory session carries one encoded WatchResponse
 * (docs/client-protocol.md). The pure path parses it with protobuf (upb) and
 * builds the client's records from the message's attributes
 * (cast.client.conversions.event_from_pb): some twenty objects and a hundred
 * C-API calls per event, which on the cold caches a watcher of 30 Hz frames
 * meets cost about 90 us per frame against 6 us warm
 * (docs/performance-m8.md, "The Python receive path in C"). This module reads
 * the same bytes straight into the records: one pass that checks the whole
 * message and makes its strings, then one per event that claims its lent
 * value, builds the ChangeEvent and hands it on.
 *
 * It decodes only what the pure path would make of the same bytes, and
 * declines (returns False, having done nothing) whatever it does not handle
 * exactly as protobuf does: a WatchResponse field other than `events`, a
 * message field given twice (protobuf merges them), groups, anything
 * malformed. The caller then takes the pure path, which answers as it always
 * did (an error included). tests/client/test_event_frames.py holds the two
 * paths to the same records, field by field, from the schema itself.
 *
 * Only the CPython API: no protobuf library, no gRPC.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

/* Field numbers of proto/cast/v1 (entry.proto, working_memory.proto) and google/protobuf. */
enum { RESP_EVENTS = 1 };
enum {
    EV_REVISION = 1, EV_OPERATION = 2, EV_ADDRESS = 3, EV_TYPE = 4, EV_SOURCE_COMPONENT = 5,
    EV_SOURCE_SA = 6, EV_VERSION = 7, EV_TIME = 8, EV_ENTRY = 9, EV_WATCH_IDS = 10, EV_SKIPPED = 11,
    EV_FIRST_SKIPPED = 12
};
enum { ADDR_ID = 1, ADDR_SA = 2 };
enum {
    ENTRY_ADDRESS = 1, ENTRY_TYPE = 2, ENTRY_VALUE = 3, ENTRY_VERSION = 4, ENTRY_AUTHOR = 5,
    ENTRY_MODIFIED = 6, ENTRY_REVISION = 7, ENTRY_SHARED = 8
};
enum { ANY_VALUE = 2 };
enum { TS_SECONDS = 1, TS_NANOS = 2 };
enum { SV_SEGMENT = 1, SV_OFFSET = 2, SV_SIZE = 3, SV_VALUE_ID = 4 };
enum { WT_VARINT = 0, WT_I64 = 1, WT_LEN = 2, WT_I32 = 5 };

/* What configure() was given: the record classes and the operations by number. */
static PyObject *event_cls, *entry_cls, *operations, *operation_cls, *empty_str, *empty_bytes;

typedef struct {
    const uint8_t *p, *end;
} Reader;

/* 0 and the value, or -1 for a varint that runs past the end or over ten bytes. */
static int varint(Reader *r, uint64_t *out) {
    uint64_t v = 0;
    for (int shift = 0; shift < 70; shift += 7) {
        if (r->p >= r->end) return -1;
        uint8_t b = *r->p++;
        v |= (uint64_t)(b & 0x7f) << shift;
        if (!(b & 0x80)) {
            *out = v;
            return 0;
        }
    }
    return -1;
}

/* A length-delimited field's bytes as a sub-reader. */
static int sub(Reader *r, Reader *out) {
    uint64_t n;
    if (varint(r, &n) < 0 || n > (uint64_t)(r->end - r->p)) return -1;
    out->p = r->p;
    out->end = r->p + n;
    r->p += n;
    return 0;
}

/* Skip a field of an unused number, as protobuf keeps but never shows it; groups are declined. */
static int skip(Reader *r, int wire_type) {
    uint64_t v;
    Reader ignored;
    switch (wire_type) {
    case WT_VARINT: return varint(r, &v);
    case WT_LEN: return sub(r, &ignored);
    case WT_I64:
        if (r->end - r->p < 8) return -1;
        r->p += 8;
        return 0;
    case WT_I32:
        if (r->end - r->p < 4) return -1;
        r->p += 4;
        return 0;
    default: return -1;
    }
}

/* The next field's number and wire type; -1 when malformed (number 0 included, which protobuf refuses). */
static int tag(Reader *r, uint32_t *number, int *wire_type) {
    uint64_t t;
    if (varint(r, &t) < 0 || (t >> 3) == 0 || (t >> 3) > 0x1fffffff) return -1;
    *number = (uint32_t)(t >> 3);
    *wire_type = (int)(t & 7);
    return 0;
}

/* A varint field's value; the field must have wire type VARINT (protobuf refuses another for a scalar). */
static int scalar(Reader *r, int wire_type, uint64_t *out) {
    return wire_type == WT_VARINT ? varint(r, out) : -1;
}

/* A string field (the last one given wins, as in protobuf); UTF-8 checked as protobuf checks proto3 strings. */
static int string(Reader *r, int wire_type, PyObject **slot) {
    Reader s;
    if (wire_type != WT_LEN || sub(r, &s) < 0) return -1;
    PyObject *str = PyUnicode_DecodeUTF8((const char *)s.p, s.end - s.p, "strict");
    if (str == NULL) {
        PyErr_Clear();
        return -1;
    }
    Py_XSETREF(*slot, str);
    return 0;
}

/* A message field, at most once: protobuf merges a repeated one, which this module does not do. */
static int message(Reader *r, int wire_type, int *seen, Reader *out) {
    if (wire_type != WT_LEN || *seen) return -1;
    *seen = 1;
    return sub(r, out);
}

typedef struct {
    int64_t seconds;
    int32_t nanos;
} Time;

static int timestamp(Reader m, Time *t) {
    uint32_t n;
    int wt;
    uint64_t v;
    while (m.p < m.end) {
        if (tag(&m, &n, &wt) < 0) return -1;
        if (n == TS_SECONDS) {
            if (scalar(&m, wt, &v) < 0) return -1;
            t->seconds = (int64_t)v;
        } else if (n == TS_NANOS) {
            if (scalar(&m, wt, &v) < 0) return -1;
            t->nanos = (int32_t)(uint32_t)v;
        } else if (skip(&m, wt) < 0) {
            return -1;
        }
    }
    return 0;
}

/* Nanoseconds since the epoch, as cast.wire.values.ns: seconds * 10**9 + nanos, as a Python int. */
static PyObject *nanoseconds(Time t) {
    if (t.seconds > -9000000000LL && t.seconds < 9000000000LL)
        return PyLong_FromLongLong(t.seconds * 1000000000LL + t.nanos);
    PyObject *s = PyLong_FromLongLong(t.seconds), *g = PyLong_FromLong(1000000000L), *n = PyLong_FromLong(t.nanos);
    PyObject *sg = s && g ? PyNumber_Multiply(s, g) : NULL;
    PyObject *out = sg && n ? PyNumber_Add(sg, n) : NULL;
    Py_XDECREF(s);
    Py_XDECREF(g);
    Py_XDECREF(n);
    Py_XDECREF(sg);
    return out;
}

static int address(Reader m, PyObject **sa, PyObject **id) {
    uint32_t n;
    int wt;
    while (m.p < m.end) {
        if (tag(&m, &n, &wt) < 0) return -1;
        if (n == ADDR_ID) {
            if (string(&m, wt, id) < 0) return -1;
        } else if (n == ADDR_SA) {
            if (string(&m, wt, sa) < 0) return -1;
        } else if (skip(&m, wt) < 0) {
            return -1;
        }
    }
    return 0;
}

/* One event of the frame, checked and with its strings made: what the second pass builds records of. */
typedef struct {
    uint64_t revision, version, skipped, first_skipped;
    int32_t operation;
    Time time;
    PyObject *sa, *id, *type, *source_component, *source_sa;
    PyObject *watch_ids; /* a list of ints */
    int has_entry;
    struct {
        PyObject *sa, *id, *type, *author, *data;
        uint64_t version, revision;
        Time modified;
        int has_shared;
        uint64_t segment, offset, size, value_id;
    } entry;
} Event;

static void event_clear(Event *e) {
    Py_CLEAR(e->sa);
    Py_CLEAR(e->id);
    Py_CLEAR(e->type);
    Py_CLEAR(e->source_component);
    Py_CLEAR(e->source_sa);
    Py_CLEAR(e->watch_ids);
    Py_CLEAR(e->entry.sa);
    Py_CLEAR(e->entry.id);
    Py_CLEAR(e->entry.type);
    Py_CLEAR(e->entry.author);
    Py_CLEAR(e->entry.data);
}

static int any_value(Reader m, PyObject **data) {
    uint32_t n;
    int wt;
    while (m.p < m.end) {
        if (tag(&m, &n, &wt) < 0) return -1;
        if (n == ANY_VALUE) {
            Reader s;
            if (wt != WT_LEN || sub(&m, &s) < 0) return -1;
            PyObject *b = PyBytes_FromStringAndSize((const char *)s.p, s.end - s.p);
            if (b == NULL) return -1;
            Py_XSETREF(*data, b);
        } else if (n == 1) { /* type_url: a string protobuf checks, not used by the records */
            PyObject *url = NULL;
            if (string(&m, wt, &url) < 0) return -1;
            Py_DECREF(url);
        } else if (skip(&m, wt) < 0) {
            return -1;
        }
    }
    return 0;
}

static int shared_value(Reader m, Event *e) {
    uint32_t n;
    int wt;
    uint64_t v;
    while (m.p < m.end) {
        if (tag(&m, &n, &wt) < 0) return -1;
        if (n >= SV_SEGMENT && n <= SV_VALUE_ID) {
            if (scalar(&m, wt, &v) < 0) return -1;
            if (n == SV_SEGMENT) e->entry.segment = (uint32_t)v; /* uint32: protobuf keeps the low 32 bits */
            else if (n == SV_OFFSET) e->entry.offset = v;
            else if (n == SV_SIZE) e->entry.size = v;
            else e->entry.value_id = v;
        } else if (skip(&m, wt) < 0) {
            return -1;
        }
    }
    return 0;
}

static int entry(Reader m, Event *e) {
    uint32_t n;
    int wt;
    uint64_t v;
    int seen_address = 0, seen_value = 0, seen_modified = 0, seen_shared = 0;
    Reader s;
    while (m.p < m.end) {
        if (tag(&m, &n, &wt) < 0) return -1;
        switch (n) {
        case ENTRY_ADDRESS:
            if (message(&m, wt, &seen_address, &s) < 0 || address(s, &e->entry.sa, &e->entry.id) < 0) return -1;
            break;
        case ENTRY_TYPE:
            if (string(&m, wt, &e->entry.type) < 0) return -1;
            break;
        case ENTRY_VALUE:
            if (message(&m, wt, &seen_value, &s) < 0 || any_value(s, &e->entry.data) < 0) return -1;
            break;
        case ENTRY_VERSION:
            if (scalar(&m, wt, &v) < 0) return -1;
            e->entry.version = v;
            break;
        case ENTRY_AUTHOR:
            if (string(&m, wt, &e->entry.author) < 0) return -1;
            break;
        case ENTRY_MODIFIED:
            if (message(&m, wt, &seen_modified, &s) < 0 || timestamp(s, &e->entry.modified) < 0) return -1;
            break;
        case ENTRY_REVISION:
            if (scalar(&m, wt, &v) < 0) return -1;
            e->entry.revision = v;
            break;
        case ENTRY_SHARED:
            if (message(&m, wt, &seen_shared, &s) < 0 || shared_value(s, e) < 0) return -1;
            e->entry.has_shared = 1;
            break;
        default:
            if (skip(&m, wt) < 0) return -1;
        }
    }
    return 0;
}

/* watch_ids (uint32, repeated): packed or one by one, as protobuf accepts either. */
static int watch_ids(Reader *r, int wire_type, Event *e) {
    uint64_t v;
    if (e->watch_ids == NULL && (e->watch_ids = PyList_New(0)) == NULL) return -1;
    Reader packed = *r, *from = r;
    if (wire_type == WT_LEN) {
        if (sub(r, &packed) < 0) return -1;
        from = &packed;
    } else if (wire_type != WT_VARINT) {
        return -1;
    }
    /* One value unpacked; a packed field's every value, none when it is empty. */
    for (int first = 1; wire_type == WT_LEN ? packed.p < packed.end : first; first = 0) {
        if (varint(from, &v) < 0) return -1;
        PyObject *id = PyLong_FromUnsignedLong((uint32_t)v);
        if (id == NULL) return -1;
        int failed = PyList_Append(e->watch_ids, id);
        Py_DECREF(id);
        if (failed) return -1;
    }
    return 0;
}

static int event(Reader m, Event *e) {
    uint32_t n;
    int wt;
    uint64_t v;
    int seen_address = 0, seen_time = 0, seen_entry = 0;
    Reader s;
    while (m.p < m.end) {
        if (tag(&m, &n, &wt) < 0) return -1;
        switch (n) {
        case EV_REVISION:
        case EV_VERSION:
        case EV_SKIPPED:
        case EV_FIRST_SKIPPED:
            if (scalar(&m, wt, &v) < 0) return -1;
            *(n == EV_REVISION ? &e->revision : n == EV_VERSION ? &e->version
              : n == EV_SKIPPED ? &e->skipped : &e->first_skipped) = v;
            break;
        case EV_OPERATION:
            if (scalar(&m, wt, &v) < 0) return -1;
            e->operation = (int32_t)(uint32_t)v; /* an enum is an int32 on the wire */
            break;
        case EV_ADDRESS:
            if (message(&m, wt, &seen_address, &s) < 0 || address(s, &e->sa, &e->id) < 0) return -1;
            break;
        case EV_TYPE:
            if (string(&m, wt, &e->type) < 0) return -1;
            break;
        case EV_SOURCE_COMPONENT:
            if (string(&m, wt, &e->source_component) < 0) return -1;
            break;
        case EV_SOURCE_SA:
            if (string(&m, wt, &e->source_sa) < 0) return -1;
            break;
        case EV_TIME:
            if (message(&m, wt, &seen_time, &s) < 0 || timestamp(s, &e->time) < 0) return -1;
            break;
        case EV_ENTRY:
            if (message(&m, wt, &seen_entry, &s) < 0 || entry(s, e) < 0) return -1;
            e->has_entry = 1;
            break;
        case EV_WATCH_IDS:
            if (watch_ids(&m, wt, e) < 0) return -1;
            break;
        default:
            if (skip(&m, wt) < 0) return -1;
        }
    }
    return 0;
}

/* A str slot as the record takes it: "" when the field was not given. */
static PyObject *text(PyObject *s) {
    return s != NULL ? s : empty_str;
}

/* The ChangeEvent of one checked event, its lent value claimed; a new reference, or NULL with the error set. */
static PyObject *record(Event *e, PyObject *claim) {
    PyObject *entry_record = NULL, *lease = Py_None, *claimed = NULL, *data, *operation, *out = NULL;
    /* _OPERATIONS.get(op) or Operation(op), before the claim as in the pure path: an unknown number raises. */
    PyObject *number = PyLong_FromLong(e->operation);
    if (number == NULL) return NULL;
    operation = PyDict_GetItemWithError(operations, number);
    if (operation != NULL) {
        Py_INCREF(operation);
    } else if (!PyErr_Occurred()) {
        operation = PyObject_CallOneArg(operation_cls, number);
    }
    Py_DECREF(number);
    if (operation == NULL) return NULL;
    if (e->has_entry) {
        data = e->entry.data != NULL ? e->entry.data : empty_bytes;
        if (e->entry.has_shared) {
            claimed = PyObject_CallFunction(claim, "KKKK", (unsigned long long)e->entry.segment,
                                            (unsigned long long)e->entry.offset, (unsigned long long)e->entry.size,
                                            (unsigned long long)e->entry.value_id);
            if (claimed == NULL) goto done;
            if (!PyTuple_Check(claimed) || PyTuple_GET_SIZE(claimed) != 2) {
                PyErr_SetString(PyExc_TypeError, "claim must return (data, lease)");
                goto done;
            }
            data = PyTuple_GET_ITEM(claimed, 0);
            lease = PyTuple_GET_ITEM(claimed, 1);
        }
        PyObject *version = PyLong_FromUnsignedLongLong(e->entry.version);
        PyObject *modified = nanoseconds(e->entry.modified);
        PyObject *revision = PyLong_FromUnsignedLongLong(e->entry.revision);
        if (version && modified && revision) {
            PyObject *args[] = {text(e->entry.sa), text(e->entry.id), text(e->entry.type), data, version,
                                text(e->entry.author), modified, revision, lease};
            entry_record = PyObject_Vectorcall(entry_cls, args, 9, NULL);
        }
        Py_XDECREF(version);
        Py_XDECREF(modified);
        Py_XDECREF(revision);
        if (entry_record == NULL) goto done;
    }
    PyObject *time_ns = nanoseconds(e->time), *seq = PyLong_FromLong(0);
    PyObject *revision = PyLong_FromUnsignedLongLong(e->revision), *version = PyLong_FromUnsignedLongLong(e->version);
    if (time_ns && seq && revision && version) {
        PyObject *args[] = {seq, revision, operation, text(e->sa), text(e->id), text(e->type),
                            text(e->source_component), text(e->source_sa), version, time_ns,
                            entry_record != NULL ? entry_record : Py_None};
        out = PyObject_Vectorcall(event_cls, args, 11, NULL);
    }
    Py_XDECREF(time_ns);
    Py_XDECREF(seq);
    Py_XDECREF(revision);
    Py_XDECREF(version);
    if (out != NULL && e->skipped) {
        PyObject *skipped = PyLong_FromUnsignedLongLong(e->skipped);
        PyObject *first = PyLong_FromUnsignedLongLong(e->first_skipped);
        if (skipped == NULL || first == NULL || PyObject_SetAttrString(out, "skipped", skipped) < 0
            || PyObject_SetAttrString(out, "first_skipped_revision", first) < 0)
            Py_CLEAR(out);
        Py_XDECREF(skipped);
        Py_XDECREF(first);
    }
done:
    Py_DECREF(operation);
    Py_XDECREF(claimed);
    Py_XDECREF(entry_record);
    return out;
}

/* seen[sa] = max(seen.get(sa, 0), revision): how far the stream has read each WM. */
static int note_seen(PyObject *seen, PyObject *sa, uint64_t revision) {
    PyObject *before = PyDict_GetItemWithError(seen, sa);
    if (before == NULL && PyErr_Occurred()) return -1;
    if (before != NULL) {
        unsigned long long had = PyLong_AsUnsignedLongLong(before);
        if (had == (unsigned long long)-1 && PyErr_Occurred()) return -1;
        if (revision <= had) return 0;
    } else if (revision == 0) {
        return 0;
    }
    PyObject *r = PyLong_FromUnsignedLongLong(revision);
    if (r == NULL) return -1;
    int failed = PyDict_SetItem(seen, sa, r);
    Py_DECREF(r);
    return failed;
}

PyDoc_STRVAR(turn_doc,
"turn(body, claim, sink, seen) -> bool\n\n"
"The events of one EVENTS frame's WatchResponse ``body`` (bytes or a buffer), in order: each lent value\n"
"claimed with ``claim(segment, offset, size, value_id) -> (data, lease)``, each ChangeEvent handed to\n"
"``sink(event, watch_ids)``, ``seen[sa]`` raised to its revision. False, having done nothing, when the\n"
"message holds what only protobuf decodes (the caller then takes the pure path); an error of claim or\n"
"sink ends it there, the events before handed on.");

static PyObject *turn(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "turn(body, claim, sink, seen) takes 4 arguments");
        return NULL;
    }
    if (event_cls == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "call configure() before turn()");
        return NULL;
    }
    PyObject *claim = args[1], *sink = args[2], *seen = args[3];
    if (!PyDict_Check(seen)) {
        PyErr_SetString(PyExc_TypeError, "seen must be a dict");
        return NULL;
    }
    Py_buffer body;
    if (PyObject_GetBuffer(args[0], &body, PyBUF_SIMPLE) < 0) return NULL;
    Reader r = {(const uint8_t *)body.buf, (const uint8_t *)body.buf + body.len};
    Event *events = NULL;
    Py_ssize_t count = 0, room = 0;
    PyObject *result = NULL;
    int declined = 0;
    while (r.p < r.end && !declined) {
        uint32_t n;
        int wt;
        Reader s;
        if (tag(&r, &n, &wt) < 0 || n != RESP_EVENTS || wt != WT_LEN || sub(&r, &s) < 0) {
            declined = 1;
            break;
        }
        if (count == room) {
            Py_ssize_t more = room ? room * 2 : 4;
            Event *grown = PyMem_Realloc(events, more * sizeof(Event));
            if (grown == NULL) {
                PyErr_NoMemory();
                goto end;
            }
            events = grown;
            room = more;
        }
        memset(&events[count], 0, sizeof(Event));
        count++;
        if (event(s, &events[count - 1]) < 0) {
            if (PyErr_Occurred()) goto end; /* out of memory, not a message protobuf would refuse */
            declined = 1;
        }
    }
    if (declined) {
        result = Py_False;
        Py_INCREF(result);
        goto end;
    }
    for (Py_ssize_t i = 0; i < count; i++) {
        Event *e = &events[i];
        PyObject *change = record(e, claim);
        if (change == NULL) goto end;
        PyObject *ids = e->watch_ids != NULL ? e->watch_ids : PyList_New(0);
        PyObject *done = ids != NULL ? PyObject_CallFunctionObjArgs(sink, change, ids, NULL) : NULL;
        if (e->watch_ids == NULL) Py_XDECREF(ids);
        Py_DECREF(change);
        if (done == NULL) goto end;
        Py_DECREF(done);
        if (note_seen(seen, text(e->sa), e->revision) < 0) goto end;
    }
    result = Py_True;
    Py_INCREF(result);
end:
    for (Py_ssize_t i = 0; i < count; i++) event_clear(&events[i]);
    PyMem_Free(events);
    PyBuffer_Release(&body);
    return result;
}

PyDoc_STRVAR(configure_doc,
"configure(event_cls, entry_cls, operations, operation_cls)\n\n"
"The classes turn() builds (ChangeEvent, EntryRecord), the operations by number (a dict) and the\n"
"Operation enum an unknown number is given to.");

static PyObject *configure(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *ev, *en, *ops, *op;
    if (!PyArg_ParseTuple(args, "OOO!O", &ev, &en, &PyDict_Type, &ops, &op)) return NULL;
    Py_INCREF(ev);
    Py_INCREF(en);
    Py_INCREF(ops);
    Py_INCREF(op);
    Py_XSETREF(event_cls, ev);
    Py_XSETREF(entry_cls, en);
    Py_XSETREF(operations, ops);
    Py_XSETREF(operation_cls, op);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"turn", (PyCFunction)(void (*)(void))turn, METH_FASTCALL, turn_doc},
    {"configure", configure, METH_VARARGS, configure_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "cast.client._events_native",
    "EVENTS frames turned into change events in C (cast.client.conversions.turn_events uses it).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__events_native(void) {
    empty_str = PyUnicode_FromStringAndSize("", 0);
    empty_bytes = PyBytes_FromStringAndSize("", 0);
    if (empty_str == NULL || empty_bytes == NULL) return NULL;
    return PyModule_Create(&module);
}
