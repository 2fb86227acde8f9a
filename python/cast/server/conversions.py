"""Conversions of the server: the core's records to wire messages (cast.v1), and requests' filters back.

Event encodings are cached on the event and reused for every stream (see
:func:`watch_events_wire`); they are written field by field
(:mod:`cast.server.event_encoding`), the rest with protobuf's messages. No
gRPC here. The client's direction is :mod:`cast.client.conversions`.
"""

from __future__ import annotations

from cast.core.arena import Placed
from cast.core.records import ChangeEvent, EntryRecord, Operation
from cast.core.shared import Lent
from cast.core.tasks import TaskRecord
from cast.core.watch import EventFilter
from cast.errors import InvalidArgumentError
from cast.server.event_encoding import entry_head, entry_reference, event_head
from cast.v1 import entry_pb2, task_manager_pb2
from cast.wire.values import TYPE_URL_PREFIX, any_of, timestamp, varint

__all__ = [
    "BY_REFERENCE",
    "entry_to_pb",
    "event_wire",
    "fill_entry",
    "filter_from_pb",
    "task_to_pb",
    "watch_events_wire",
]


def entry_to_pb(record: EntryRecord) -> entry_pb2.Entry:
    """Wire form of a stored entry."""
    pb = entry_pb2.Entry()
    fill_entry(pb, record)
    return pb


BY_REFERENCE = 2
"""An event's ``include_entry`` in :func:`watch_events_wire` when its entry's value goes by reference."""


def fill_entry(pb: entry_pb2.Entry, record: EntryRecord, lent: Lent | None = None) -> None:
    """Write a stored entry into ``pb`` in place; ``lent``: its value goes by reference (``shared_value``).

    Setting the fields of a message in place costs about a third of building the
    nested messages and copying them in, and this is on the path of every read.
    """
    pb.address.id = record.id
    pb.address.subarchitecture = record.subarchitecture
    pb.type = record.type
    pb.value.type_url = TYPE_URL_PREFIX + record.type
    if lent is not None:
        shared = pb.shared_value
        shared.segment, shared.offset = lent.segment, lent.offset
        shared.size, shared.value_id = lent.size, lent.value_id
    else:
        data = record.data
        pb.value.value = data if isinstance(data, bytes) else bytes(data)
    pb.version = record.version
    pb.author = record.author
    pb.modified.seconds, pb.modified.nanos = divmod(record.modified_ns, 1_000_000_000)
    pb.revision = record.revision


def event_wire(ev: ChangeEvent, include_entry: int) -> tuple[bytes, bytes | memoryview]:
    """The encoded ``cast.v1.ChangeEvent`` without watch ids, as ``(head, value)``: send ``head + value``.

    ``head`` is cached on the event; ``value`` is the stored entry's own bytes
    (empty without the entry), so the history holds one copy of each value
    however many streams carry it - a 1 MiB image is not kept twice. The
    entry's ``value`` field is encoded last, which protobuf allows (fields may
    come in any order), so that its bytes can follow the cached part as they are.
    ``include_entry`` :data:`BY_REFERENCE`: the entry's value in shared memory
    is named (``shared_value``) instead, the same for every reader it is lent to.
    """
    cache = ev.wire
    if cache is None:
        cache = ev.wire = [None, None, None]
    record = ev.entry if include_entry else None
    slot = 0 if record is None else (2 if include_entry == BY_REFERENCE else 1)
    head = cache[slot]
    if head is None:
        head = cache[0]
        if head is None:
            head = cache[0] = event_head(ev)
        if record is not None:
            if slot == 2:
                placed = record.shared
                assert isinstance(placed, Placed)
                entry = entry_reference(record, Lent(placed.segment, placed.offset, placed.length, placed.value_id))
                size = 0
            else:
                entry = entry_head(record)
                size = len(record.data)
            head = cache[slot] = head + _EVENT_ENTRY_TAG + varint(len(entry) + size) + entry
    if slot == 1:
        return head, record.data  # type: ignore[union-attr]
    return head, b""


_EVENT_ENTRY_TAG = b"\x4a"  # ChangeEvent.entry: field 9, length-delimited
_EVENTS_TAG = b"\x0a"  # WatchResponse.events: field 1, length-delimited
_WATCH_IDS_TAG = b"\x52"  # ChangeEvent.watch_ids: field 10, packed
_SKIPPED_TAG = b"\x58"  # ChangeEvent.skipped: field 11, varint
_FIRST_SKIPPED_TAG = b"\x60"  # ChangeEvent.first_skipped_revision: field 12, varint


def watch_events_wire(events: list[tuple[ChangeEvent, list[int], int, int, int]]) -> bytes:
    """An encoded ``cast.v1.WatchResponse`` of ``(event, watch_ids, include_entry, skipped, first_skipped)``.

    Protobuf lets fields of a message be concatenated, so each event's cached
    encoding is reused as is and only what is this stream's own is appended
    (its watch ids, and what a latest-delivery watch skipped): fan-out to many
    streams costs one encoding per event, not one per event per stream.
    """
    parts: list[bytes | memoryview] = []
    for ev, watch_ids, include, skipped, first_skipped in events:
        head, value = event_wire(ev, include)
        packed = bytes(watch_ids) if all(i < 0x80 for i in watch_ids) else b"".join(varint(i) for i in watch_ids)
        tail = _WATCH_IDS_TAG + varint(len(packed)) + packed
        if skipped:
            tail += _SKIPPED_TAG + varint(skipped) + _FIRST_SKIPPED_TAG + varint(first_skipped)
        parts.extend((_EVENTS_TAG, varint(len(head) + len(value) + len(tail)), head, value, tail))
    return b"".join(parts)


def filter_from_pb(pb: entry_pb2.ChangeFilter) -> EventFilter:
    """Core filter from a wire filter; INVALID_ARGUMENT for an unknown operation."""
    ops = set()
    for op in pb.operations:
        if op == entry_pb2.OPERATION_UNSPECIFIED:
            continue
        try:
            ops.add(Operation(op))
        except ValueError:
            raise InvalidArgumentError(f"unknown operation {op} in a change filter") from None
    return EventFilter(
        frozenset(ops),
        pb.type,
        pb.id,
        pb.subarchitecture,
        pb.source_component,
        pb.source_subarchitecture,
        pb.include_entry,
    )


def task_to_pb(task: TaskRecord) -> task_manager_pb2.Task:
    """Wire form of a task."""
    pb = task_manager_pb2.Task(
        task_id=task.task_id,
        name=task.name,
        subarchitecture=task.subarchitecture,
        component=task.component,
        priority=task.priority,
        state=task.state,  # type: ignore[arg-type]
        outcome=task.outcome,  # type: ignore[arg-type]
        reason=task.reason,
        proposed=timestamp(task.proposed_ns),
    )
    if task.data_type:
        pb.data.CopyFrom(any_of(task.data_type, task.data))
    if task.decided_ns:
        pb.decided.CopyFrom(timestamp(task.decided_ns))
    return pb
