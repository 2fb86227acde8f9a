"""The once-encoded events of watch streams: what they decode to, one copy of each value, protobuf's own bytes."""

from __future__ import annotations

import pytest

from cast.core.arena import Arena
from cast.core.records import BatchOp, ChangeEvent, EntryRecord, Identity, Operation
from cast.core.shared import Lent
from cast.server.conversions import BY_REFERENCE, entry_to_pb, event_wire, fill_entry, watch_events_wire
from cast.server.event_encoding import entry_head, entry_reference, event_head
from cast.server.wire import wire_system
from cast.v1 import entry_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire.values import timestamp

WHO = Identity("w", "vision")


def event_to_pb(ev: ChangeEvent, watch_ids: list[int], include_entry: bool) -> entry_pb2.ChangeEvent:
    """The event for one stream, built with protobuf's messages: what the hand-written encoding must equal."""
    pb = entry_pb2.ChangeEvent(
        revision=ev.revision,
        operation=ev.operation,  # type: ignore[arg-type]  # IntEnum values equal the wire enum
        address=entry_pb2.EntryAddress(id=ev.id, subarchitecture=ev.subarchitecture),
        type=ev.type,
        source_component=ev.source_component,
        source_subarchitecture=ev.source_subarchitecture,
        version=ev.version,
        time=timestamp(ev.time_ns),
        watch_ids=watch_ids,
    )
    if include_entry and ev.entry is not None:
        pb.entry.CopyFrom(entry_to_pb(ev.entry))
    return pb


# Records and events at the edges of each field: defaults (left out), text beyond ASCII, varints of every length.
RECORDS = [
    EntryRecord("vision", "img", "t.Image", b"\x01" * 300, 1, "camera", 1_700_000_000_123_456_789, 5),
    EntryRecord("vision", "img", "t.Image", b"", 2, "camera", 1_700_000_000_000_000_000, 6),  # an empty value
    EntryRecord("vïsion", "imagé/ß", "", b"x", 0, "", 0, 0),  # every default, and no type
    EntryRecord("s" * 200, "i" * 300, "a.B" * 50, b"y" * 70_000, (1 << 64) - 1, "c" * 130, (1 << 62) + 7, 1 << 63),
]
EVENTS = [
    ChangeEvent(1, 5, Operation.ADD, "vision", "img", "t.Image", "camera", "vision", 1, 1_700_000_000_999_999_999,
                RECORDS[0]),
    ChangeEvent(2, 6, Operation.OVERWRITE, "vision", "img", "t.Image", "camera", "", 2, 1_700_000_001_000_000_000,
                RECORDS[1]),
    ChangeEvent(3, 0, Operation.DELETE, "vïsion", "imagé/ß", "", "", "", 0, 0, RECORDS[2]),
    ChangeEvent(4, 1 << 63, Operation.OVERWRITE, "s" * 200, "i" * 300, "a.B" * 50, "c" * 130, "d" * 140,
                (1 << 64) - 1, (1 << 62) + 7, RECORDS[3]),
    ChangeEvent(5, 9, Operation.ADD, "vision", "img", "t.Image", "camera", "vision", 1, -1_500_000_000,
                RECORDS[0]),  # before 1970: a negative int64 of seconds, in ten bytes
]


@pytest.mark.parametrize("ev", EVENTS)
def test_an_event_head_is_protobufs_own_encoding(ev: ChangeEvent) -> None:
    assert event_head(ev) == event_to_pb(ev, [], False).SerializeToString()


@pytest.mark.parametrize("record", RECORDS)
def test_an_entry_lent_by_reference_is_protobufs_own_encoding(record: EntryRecord) -> None:
    lent = Lent(3, 1 << 40, len(record.data), (1 << 64) - 2)
    want = entry_pb2.Entry()
    fill_entry(want, record, lent)
    assert entry_reference(record, lent) == want.SerializeToString()
    assert entry_reference(record, Lent(0, 0, 0, 0)) != want.SerializeToString()  # the reference is in the bytes


@pytest.mark.parametrize("record", RECORDS)
def test_an_entry_head_and_its_value_decode_to_the_entry(record: EntryRecord) -> None:
    encoded = entry_head(record) + bytes(record.data)
    assert entry_pb2.Entry.FromString(encoded) == entry_to_pb(record)


def test_an_event_by_reference_decodes_to_its_entry_naming_where_the_value_lies() -> None:
    arena = Arena(max_bytes=8 << 20, segment_bytes=4 << 20)
    try:
        placed = arena.put(b"\x05" * 100_000)
        assert placed is not None
        record = EntryRecord("vision", "img", "t.Image", placed.view, 3, "camera", 1_700_000_000_500_000_000, 7, placed)
        ev = ChangeEvent(1, 7, Operation.OVERWRITE, "vision", "img", "t.Image", "camera", "vision", 3,
                         1_700_000_000_600_000_000, record)
        head, value = event_wire(ev, BY_REFERENCE)
        assert value == b"" and len(head) < 200
        want = event_to_pb(ev, [], False)
        fill_entry(want.entry, record, Lent(placed.segment, placed.offset, placed.length, placed.value_id))
        assert head == want.SerializeToString()
        del record, ev, placed
    finally:
        arena.close()


def test_an_encoded_batch_decodes_to_the_events_with_their_entries_ids_and_skips() -> None:
    system = wire_system("t", ["vision"])
    image = bytes(range(256)) * 4096  # 1 MiB
    system.host.write(WHO, BatchOp(Operation.ADD, "vision", "img", "t.Image", image))
    system.host.write(WHO, BatchOp(Operation.OVERWRITE, "vision", "img", "t.Image", b""))  # an empty value
    system.host.write(WHO, BatchOp(Operation.DELETE, "vision", "img"))
    events = system.host.events_since("vision", 1)
    items = [(events[0], [1, 300], True, 0, 0), (events[1], [2], True, 4, 1), (events[2], [1], False, 0, 0)]
    decoded = wm_pb2.WatchResponse.FromString(watch_events_wire(items)).events
    for got, (ev, ids, include, skipped, first) in zip(decoded, items, strict=True):
        want = event_to_pb(ev, ids, include)
        want.skipped, want.first_skipped_revision = skipped, first
        assert got == want
    assert decoded[0].entry.value.value == image and decoded[1].entry.value.value == b""


def test_the_cached_encoding_holds_no_copy_of_the_value() -> None:
    system = wire_system("t", ["vision"])
    image = b"\x07" * (1024 * 1024)
    system.host.write(WHO, BatchOp(Operation.ADD, "vision", "img", "t.Image", image))
    (event,) = system.host.events_since("vision", 1)
    assert event.entry is not None
    head, value = event_wire(event, True)
    assert value is event.entry.data  # the stored bytes themselves
    assert len(head) < 200 and event.wire is not None
    assert all(part is None or len(part) < 200 for part in event.wire)
