"""A change event's encoding written field by field, without protobuf's message objects.

What :func:`cast.server.conversions.event_wire` caches on each event: the
``cast.v1.ChangeEvent`` without its watch ids, and its ``entry`` up to (not
including) the value's bytes or naming the value in shared memory. Building
and serialising a ``ChangeEvent`` and an ``Entry`` message cost about 55 µs
of the server's pass over its watchers on every 30 Hz frame, nearly all of it
protobuf's objects on cold caches (docs/performance-m8.md, "The write hop
without protobuf's objects"); this module writes the same bytes with the
compiled build's byte operations. The output is protobuf's own serialisation
(fields in number order, proto3 defaults left out, message fields present
when the message builder would have set them), which
tests/integration/test_event_encoding.py holds byte for byte against
protobuf's.
"""

from __future__ import annotations

from cast.core.records import ChangeEvent, EntryRecord
from cast.core.shared import Lent
from cast.wire.values import TYPE_URL_PREFIX, put_varint

__all__ = ["entry_head", "entry_reference", "event_head"]

_U64 = (1 << 64) - 1  # a negative int64 goes on the wire as its two's complement in ten bytes
_BILLION = 1_000_000_000


def _number(out: bytearray, key: int, n: int) -> None:
    """A varint field of ``n`` (0 or more); left out at 0, as proto3 leaves out every default."""
    if n:
        out.append(key)
        put_varint(out, n)


def _text(out: bytearray, key: int, text: str) -> None:
    if text:
        _bytes(out, key, text.encode())


def _bytes(out: bytearray, key: int, data: bytes | bytearray) -> None:
    """A length-delimited field, written even when empty: a message field set is present."""
    out.append(key)
    put_varint(out, len(data))
    out += data


def _address(entry_id: str, subarchitecture: str) -> bytearray:
    out = bytearray()
    _text(out, 0x0A, entry_id)  # EntryAddress.id = 1
    _text(out, 0x12, subarchitecture)  # EntryAddress.subarchitecture = 2
    return out


def _timestamp(ns: int) -> bytearray:
    out = bytearray()
    seconds, nanos = divmod(ns, _BILLION)
    _number(out, 0x08, seconds & _U64)  # Timestamp.seconds = 1, an int64 (negative before 1970)
    _number(out, 0x10, nanos)  # Timestamp.nanos = 2
    return out


def event_head(ev: ChangeEvent) -> bytes:
    """``cast.v1.ChangeEvent`` fields 1-8 of ``ev``: the event without its entry and watch ids."""
    out = bytearray()
    _number(out, 0x08, ev.revision)  # revision = 1
    _number(out, 0x10, int(ev.operation))  # operation = 2
    _bytes(out, 0x1A, _address(ev.id, ev.subarchitecture))  # address = 3
    _text(out, 0x22, ev.type)  # type = 4
    _text(out, 0x2A, ev.source_component)  # source_component = 5
    _text(out, 0x32, ev.source_subarchitecture)  # source_subarchitecture = 6
    _number(out, 0x38, ev.version)  # version = 7
    _bytes(out, 0x42, _timestamp(ev.time_ns))  # time = 8
    return bytes(out)


def _entry_after_value(out: bytearray, record: EntryRecord) -> None:
    """``cast.v1.Entry`` fields 4-7."""
    _number(out, 0x20, record.version)  # version = 4
    _text(out, 0x2A, record.author)  # author = 5
    _bytes(out, 0x32, _timestamp(record.modified_ns))  # modified = 6
    _number(out, 0x38, record.revision)  # revision = 7


def _type_url(record: EntryRecord) -> bytes:
    return (TYPE_URL_PREFIX + record.type).encode()


def entry_reference(record: EntryRecord, where: Lent) -> bytes:
    """``cast.v1.Entry`` of ``record`` whole, its value named where it lies in shared memory (``shared_value``)."""
    out = bytearray()
    _bytes(out, 0x0A, _address(record.id, record.subarchitecture))  # address = 1
    _text(out, 0x12, record.type)  # type = 2
    url = bytearray()
    _bytes(url, 0x0A, _type_url(record))  # Any.type_url = 1, never empty: the value has no bytes here
    _bytes(out, 0x1A, url)  # value = 3
    _entry_after_value(out, record)
    shared = bytearray()
    _number(shared, 0x08, where.segment)  # SharedValue.segment = 1
    _number(shared, 0x10, where.offset)  # SharedValue.offset = 2
    _number(shared, 0x18, where.size)  # SharedValue.size = 3
    _number(shared, 0x20, where.value_id)  # SharedValue.value_id = 4
    _bytes(out, 0x42, shared)  # shared_value = 8
    return bytes(out)


def entry_head(record: EntryRecord) -> bytes:
    """``cast.v1.Entry`` of ``record`` up to its value's bytes: every field but ``value``, then ``value``'s head.

    Protobuf lets a message's fields come in any order, so the value field
    goes last and its bytes (``record.data``, ``len(record.data)`` of them) can
    follow this as they are.
    """
    out = bytearray()
    _bytes(out, 0x0A, _address(record.id, record.subarchitecture))  # address = 1
    _text(out, 0x12, record.type)  # type = 2
    _entry_after_value(out, record)
    url = _type_url(record)
    size = len(record.data)
    value = bytearray()
    _bytes(value, 0x0A, url)  # Any.type_url = 1
    value.append(0x12)  # Any.value = 2, its bytes to follow
    put_varint(value, size)
    out.append(0x1A)  # value = 3
    put_varint(out, len(value) + size)
    out += value
    return bytes(out)
