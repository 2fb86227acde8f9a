"""The once-encoded events of watch streams: what they decode to, and one copy of each value."""

from __future__ import annotations

from cast.core.records import BatchOp, Identity, Operation
from cast.server.conversions import event_to_pb, event_wire, watch_events_wire
from cast.server.wire import wire_system
from cast.v1 import working_memory_pb2 as wm_pb2

WHO = Identity("w", "vision")


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
