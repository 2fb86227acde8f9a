"""Conversions of the Python client library: wire messages (cast.v1) to the records it hands out.

The same record types the core uses, so that a component in process and one
over gRPC see identical objects. Protobuf only; no gRPC here. The server's
direction is :mod:`cast.server.conversions`; what both share is in
:mod:`cast.wire`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from cast.core.records import ChangeEvent, EntryRecord, Operation
from cast.core.tasks import TaskOutcome, TaskRecord, TaskState
from cast.core.watch import EventFilter
from cast.errors import UnavailableError
from cast.v1 import entry_pb2, task_manager_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire.values import TYPE_URL_PREFIX, any_to_type_data, ns

if TYPE_CHECKING:
    from cast.client.shm_session import ReadCall

__all__ = [
    "NATIVE_EVENTS", "address", "entry_from_pb", "event_from_pb", "fill_write", "filter_to_pb", "native_turn",
    "task_from_pb", "turn_events",
]

# Looked up rather than called: an enum call runs enum's machinery for each event (0.3 us warm, more on the cold
# caches a watcher of frames at 30 Hz meets; docs/performance-m8.md, "Small cuts, and where each process's CPU
# goes").
_OPERATIONS = {int(op): op for op in Operation}

# EVENTS frames decoded in C where the build has it (the compiled build: setup.py, CAST_MYPYC=1): upb's message
# objects and their attributes cost a 30 Hz watcher about 90 us a frame on cold caches, the C decoder about 55 us
# less (docs/performance-m8.md, "The Python receive path in C"); CAST_NATIVE_EVENTS=0 keeps the pure path
# (docs/python.md).
_native: object | None = None
if os.environ.get("CAST_NATIVE_EVENTS", "1") != "0":
    try:
        from cast.client import _events_native as _native  # type: ignore[attr-defined, no-redef]
    except ImportError:  # a pure build (make setup's editable install): protobuf decodes them
        _native = None
if _native is not None:
    _native.configure(ChangeEvent, EntryRecord, _OPERATIONS, Operation)  # type: ignore[attr-defined]
NATIVE_EVENTS = _native is not None
"""Whether :func:`turn_events` decodes EVENTS frames in C (the compiled build, unless CAST_NATIVE_EVENTS=0)."""


def entry_from_pb(entry: entry_pb2.Entry, call: ReadCall | None = None) -> EntryRecord:
    """Record form of a wire entry (client side).

    An entry whose value was lent by shared memory (``shared_value``) holds a
    read-only view of it and its lease, from the read ``call`` it came on.
    """
    data: bytes | memoryview = entry.value.value
    lease = None
    if entry.HasField("shared_value"):
        if call is None:
            raise UnavailableError(
                f"entry '{entry.address.id}' came by shared memory on a call that named no session: read it again"
            )
        data, lease = call.claim(entry.shared_value)
    return EntryRecord(
        entry.address.subarchitecture,
        entry.address.id,
        entry.type,
        data,
        entry.version,
        entry.author,
        ns(entry.modified),
        entry.revision,
        lease,
    )


def event_from_pb(pb: entry_pb2.ChangeEvent, call: ReadCall | None = None) -> ChangeEvent:
    """Record form of a wire event (client side); ``seq`` is 0; ``call``: as :func:`entry_from_pb`."""
    event = ChangeEvent(
        0,
        pb.revision,
        _OPERATIONS.get(pb.operation) or Operation(pb.operation),  # an unknown value: Operation says so
        pb.address.subarchitecture,
        pb.address.id,
        pb.type,
        pb.source_component,
        pb.source_subarchitecture,
        pb.version,
        ns(pb.time),
        entry_from_pb(pb.entry, call) if pb.HasField("entry") else None,
    )
    if pb.skipped:
        event.skipped, event.first_skipped_revision = pb.skipped, pb.first_skipped_revision
    return event


def turn_events(
    body: bytes,
    call: ReadCall,
    sink: Callable[[ChangeEvent, Sequence[int]], None],
    seen: dict[str, int],
) -> None:
    """The events of one EVENTS frame's encoded WatchResponse, in order, each handed to ``sink(event, watch_ids)``.

    Each value lent by shared memory is claimed on ``call``, and ``seen[sa]``
    is raised to each event's revision once it was handed on; an error (a
    claim that failed, say) ends it there, the events before handed on.
    Decoded in C where the build has it; whatever the C decoder does not
    handle exactly as protobuf does (it says so, having done nothing) takes
    the pure path, so both give the same events and the same errors.
    """
    if _native is not None and _native.turn(body, call.claimer(), sink, seen):  # type: ignore[attr-defined]
        return
    for pb in wm_pb2.WatchResponse.FromString(body).events:
        event = event_from_pb(pb, call)
        sink(event, pb.watch_ids)
        if event.revision > seen.get(event.subarchitecture, 0):
            seen[event.subarchitecture] = event.revision


def native_turn() -> Callable[..., bool] | None:
    """The C decoder itself, ``turn(body, claim, sink, seen) -> handled``, where the build has it, else None.

    For a caller in C that calls it without :func:`turn_events` around it
    (cast.client._receive_native); on False it calls :func:`turn_events`.
    """
    return None if _native is None else _native.turn  # type: ignore[attr-defined]


def filter_to_pb(f: EventFilter) -> entry_pb2.ChangeFilter:
    """Wire filter from a core filter."""
    return entry_pb2.ChangeFilter(
        operations=sorted(int(op) for op in f.operations),  # type: ignore[misc]
        type=f.type,
        id=f.id,
        subarchitecture=f.subarchitecture,
        source_component=f.source_component,
        source_subarchitecture=f.source_subarchitecture,
        include_entry=f.include_entry,
    )


def task_from_pb(pb: task_manager_pb2.Task) -> TaskRecord:
    """Record form of a wire task (client side)."""
    data_type, data = any_to_type_data(pb.data) if pb.HasField("data") else ("", b"")
    return TaskRecord(
        pb.task_id,
        pb.name,
        pb.subarchitecture,
        pb.component,
        data_type,
        data,
        pb.priority,
        TaskState(pb.state),
        ns(pb.proposed),
        TaskOutcome(pb.outcome),
        pb.reason,
        ns(pb.decided) if pb.HasField("decided") else 0,
    )


def fill_write(req: wm_pb2.AddRequest | wm_pb2.OverwriteRequest, sa: str, entry_id: str, type_name: str,
                data: bytes) -> None:
    """Fill an Add or Overwrite request in place.

    In place: about a third of the cost of building the nested messages and copying them in.
    """
    req.address.id = entry_id
    req.address.subarchitecture = sa
    req.value.type_url = TYPE_URL_PREFIX + type_name
    req.value.value = data


def address(sa: str, entry_id: str) -> entry_pb2.EntryAddress:
    """The wire address of an entry."""
    return entry_pb2.EntryAddress(id=entry_id, subarchitecture=sa)
