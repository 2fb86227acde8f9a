"""A watcher that stops reading while many events are written.

The server keeps a bounded history and never buffers per watcher, so its memory
stays bounded however far the watcher falls behind; writers go on. When the
watcher reads again it gets every event in order, or, past the history, the
resynchronise signal (OUT_OF_RANGE): never a silent gap. 100,000 events in
`make test`, 1,000,000 in `make soak`.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import grpc
import psutil
from google.protobuf import any_pb2
from google.protobuf.wrappers_pb2 import Int64Value

from cast.v1 import entry_pb2, working_memory_pb2, working_memory_pb2_grpc
from tests.reliability.figures import record, soak

BATCH = 1000
IDS = 100  # writes overwrite these round-robin, so the WM itself does not grow


def _batches(stub: Any, md: Any, total: int, start: int) -> float:
    """Write ``total`` overwrites in batches; return the seconds taken."""
    value = any_pb2.Any()
    value.Pack(Int64Value(value=7))
    began = time.perf_counter()
    for b in range(total // BATCH):
        ops = [
            working_memory_pb2.BatchOperation(overwrite=working_memory_pb2.OverwriteRequest(
                address=entry_pb2.EntryAddress(id=f"k{(start + b * BATCH + i) % IDS}", subarchitecture="vision"),
                value=value))
            for i in range(BATCH)
        ]
        stub.Batch(working_memory_pb2.BatchRequest(operations=ops), metadata=md, timeout=60)
    return time.perf_counter() - began


def test_a_stalled_watcher_keeps_server_memory_bounded_and_gets_every_event_or_the_resync_signal(
    server_factory: Any,
) -> None:
    total = 1_000_000 if soak() else 100_000
    history = 20_000
    handle = server_factory({"system": "slow", "subarchitectures": {"vision": {}},
                             "limits": {"history_events": history}})
    proc = psutil.Process(handle.process.pid)
    ch = grpc.insecure_channel(handle.endpoint)
    stub = working_memory_pb2_grpc.WorkingMemoryStub(ch)
    md = (("authorization", f"Bearer {handle.token('writer', 'vision')}"),)
    value = any_pb2.Any()
    value.Pack(Int64Value(value=0))
    for i in range(IDS):
        stub.Add(working_memory_pb2.AddRequest(
            address=entry_pb2.EntryAddress(id=f"k{i}", subarchitecture="vision"), value=value), metadata=md)
    # Baseline: the same writes with nobody watching (after a warm-up), for the slowdown figure.
    _batches(stub, md, 20_000, 0)
    baseline = _batches(stub, md, total, 0)
    rss_before = proc.memory_info().rss

    release = threading.Event()

    def requests() -> Any:
        yield working_memory_pb2.WatchRequest(create=working_memory_pb2.WatchCreate(
            watch_id=1, filters=[entry_pb2.ChangeFilter(subarchitecture="vision", include_entry=True)]))
        release.wait()

    watch_md = (("authorization", f"Bearer {handle.token('slow', 'vision')}"),)
    stream = stub.Watch(requests(), metadata=watch_md)
    first = next(stream)  # the created acknowledgement; after it the watcher stops reading
    start_rev = first.created.revisions["vision"] + 1

    elapsed = _batches(stub, md, total, 0)
    rss_after = proc.memory_info().rss
    # Now read everything the stream gives.
    revisions: list[int] = []
    status = grpc.StatusCode.OK
    try:
        for resp in stream:
            revisions.extend(ev.revision for ev in resp.events)
            if revisions and revisions[-1] >= start_rev + total - 1:
                break
    except grpc.RpcError as exc:
        status = exc.code()
    release.set()
    stream.cancel()
    ch.close()

    assert revisions == list(range(start_rev, start_rev + len(revisions))), "a gap or a duplicate"
    if len(revisions) < total:
        assert status == grpc.StatusCode.OUT_OF_RANGE, "fewer events than written, and no resync signal"
    growth_mb = (rss_after - rss_before) / 2**20
    per_event = elapsed / baseline
    record("slow_watcher", {
        "events_written": total, "history_events": history, "events_received": len(revisions),
        "ended_with": status.name, "server_rss_growth_mb": round(growth_mb, 1),
        "writer_time_per_event_vs_no_watcher": round(per_event, 3),
    })
    # Bounded: the history ring (20,000 small events) is all the server keeps; far less than the events written.
    assert growth_mb < 200, f"server memory grew by {growth_mb:.0f} MB"
