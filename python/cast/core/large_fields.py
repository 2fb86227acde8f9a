"""A value's serialised form with its large ``bytes`` fields emptied: what the schema check parses instead.

Checking that a value parses as its type (:meth:`cast.core.schemas.SchemaRegistry.validate`)
with the protobuf runtime copies every ``bytes`` field into fresh memory: for
a 6 MiB image that is 6 MiB allocated, faulted in page by page and freed per
write (the server maps and unmaps each large block, :mod:`cast.server.allocator`),
tens of milliseconds on a busy machine. The bytes of a ``bytes`` field cannot
make a parse fail, so the check parses a copy of the value in which each large
one at the top level is present but empty: same fields, same order, same
presence, same verdict, and only the small rest copied.

The walk is of the top-level fields only and gives up (``None``: parse the
value as it is) on anything it does not need to understand: a group, a
truncated or malformed field (the runtime then reports it), or many small
fields before any large one.
"""

from __future__ import annotations

from collections.abc import Iterator

from google.protobuf.descriptor import Descriptor, FieldDescriptor

__all__ = ["LARGE", "bytes_fields", "largest_payload", "without_large_bytes"]

LARGE = 16 * 1024
"""A ``bytes`` field at least this long is emptied; below it, copying costs less than walking."""
_MAX_FIELDS = 64  # top-level fields walked before giving up: a value of many small fields is parsed as it is


def bytes_fields(desc: Descriptor) -> frozenset[int]:
    """The numbers of the top-level ``bytes`` fields of a message type."""
    return frozenset(f.number for f in desc.fields if f.type == FieldDescriptor.TYPE_BYTES)


def _varint(data: memoryview, at: int) -> tuple[int, int]:
    value = shift = 0
    while shift < 64:
        byte = data[at]  # IndexError past the end: the caller gives up
        at += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, at
        shift += 7
    raise ValueError("varint too long")


def _fields(view: memoryview) -> Iterator[tuple[int, int, int, int]]:
    """The top-level fields of ``view``, each as ``(number, value_at, payload, end)``.

    ``value_at`` is where the field's value begins (after its key), ``payload``
    where a length-delimited field's bytes begin (-1 for other kinds), ``end``
    where the next field begins. ValueError (or IndexError) for a group, a key
    with no wire type, or a field that runs past the end: a walk gives up there.
    """
    size, at = len(view), 0
    while at < size:
        key, value_at = _varint(view, at)
        number, kind, payload = key >> 3, key & 7, -1
        if kind == 0:
            _, end = _varint(view, value_at)
        elif kind == 1:
            end = value_at + 8
        elif kind == 5:
            end = value_at + 4
        elif kind == 2:
            length, payload = _varint(view, value_at)
            end = payload + length
        else:  # a group (or no wire type at all): the runtime judges it
            raise ValueError(f"wire type {kind}")
        if end > size:
            raise ValueError("a field past the end")
        yield number, value_at, payload, end
        at = end


def without_large_bytes(data: bytes | memoryview, numbers: frozenset[int]) -> bytes | None:
    """``data`` with each top-level ``bytes`` field among ``numbers`` of at least :data:`LARGE` bytes emptied.

    None when there is none to empty, or the walk gave up: then parse ``data``
    itself (for a malformed value that is what reports the error).
    """
    if not numbers or len(data) < LARGE:
        return None
    view = memoryview(data).cast("B")
    pieces: list[memoryview | bytes] = []
    kept, emptied = 0, False  # the start of what is still to be copied
    try:
        for fields, (number, value_at, payload, end) in enumerate(_fields(view), 1):
            if fields > _MAX_FIELDS and not emptied:
                return None
            if payload >= 0 and end - payload >= LARGE and number in numbers:
                pieces += [view[kept:value_at], b"\x00"]  # the key, then a length of 0
                kept, emptied = end, True
    except (IndexError, ValueError):
        return None
    if not emptied:
        return None
    pieces.append(view[kept:])
    return b"".join(pieces)


def largest_payload(data: bytes | memoryview) -> int:
    """Where the bytes of the largest top-level length-delimited field of at least :data:`LARGE` bytes begin.

    0 when there is none, or the walk gives up (as :func:`without_large_bytes`
    does) before it finds one. The arena aligns a value so that these bytes (an
    image's pixels) start on a cache line (:data:`cast.core.arena.ALIGN`).
    """
    if len(data) < LARGE:
        return 0
    best, best_length = 0, LARGE - 1
    try:
        for _, (_, _, payload, end) in zip(range(_MAX_FIELDS), _fields(memoryview(data).cast("B")), strict=False):
            if payload >= 0 and end - payload > best_length:
                best, best_length = payload, end - payload
    except (IndexError, ValueError):
        pass
    return best
