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


def test_a_stalled_latest_watcher_gets_the_newest_change_of_each_entry_with_what_it_skipped(
    server_factory: Any,
) -> None:
    """`latest` is for slow consumers of fast data: however long its client does not read, its watch does not
    fall behind the history (which holds 20 changes here); when it reads again it gets each entry's newest change,
    its skipped count covering every other change, in revision order."""
    entries, rounds = 4, 300
    handle = server_factory({"system": "slow", "subarchitectures": {"vision": {}},
                             "limits": {"history_events": 20}})
    ch = grpc.insecure_channel(handle.endpoint)
    stub = working_memory_pb2_grpc.WorkingMemoryStub(ch)
    md = (("authorization", f"Bearer {handle.token('writer', 'vision')}"),)
    pixels = b"\x07" * (256 << 10)  # the client's flow-control window fills after a few of these
    for i in range(entries):
        stub.Add(working_memory_pb2.AddRequest(
            address=entry_pb2.EntryAddress(id=f"img{i}", subarchitecture="vision"),
            value=any_pb2.Any(type_url="type.googleapis.com/google.protobuf.BytesValue")), metadata=md)
    release = threading.Event()

    def requests() -> Any:
        yield working_memory_pb2.WatchRequest(create=working_memory_pb2.WatchCreate(
            watch_id=1, delivery=working_memory_pb2.DELIVERY_LATEST,
            filters=[entry_pb2.ChangeFilter(subarchitecture="vision", include_entry=True)]))
        release.wait()

    stream = stub.Watch(requests(), metadata=(("authorization", f"Bearer {handle.token('slow', 'vision')}"),))
    first = next(stream)  # created; the watcher stops reading now
    start = first.created.revisions["vision"] + 1
    for r in range(rounds):
        ops = [working_memory_pb2.BatchOperation(overwrite=working_memory_pb2.OverwriteRequest(
            address=entry_pb2.EntryAddress(id=f"img{i}", subarchitecture="vision"),
            value=any_pb2.Any(type_url="type.googleapis.com/google.protobuf.BytesValue",
                              value=b"\x0a" + _varint(len(pixels) + 8) + r.to_bytes(8, "little") + pixels)))
            for i in range(entries)]
        stub.Batch(working_memory_pb2.BatchRequest(operations=ops), metadata=md, timeout=60)
    last = start + entries * rounds - 1
    got: list[tuple[int, str, int]] = []  # revision, entry, skipped
    status = grpc.StatusCode.OK
    try:
        for resp in stream:
            got.extend((ev.revision, ev.entry.address.id, ev.skipped) for ev in resp.events)
            if got and got[-1][0] >= last:
                break
    except grpc.RpcError as exc:
        status = exc.code()
    release.set()
    stream.cancel()
    ch.close()
    assert status == grpc.StatusCode.OK, f"the latest watch ended with {status.name} after {len(got)} events"
    revisions = [g[0] for g in got]
    assert revisions == sorted(set(revisions)), "out of order or twice"
    assert sum(1 + skipped for _, _, skipped in got) == entries * rounds, "a change neither received nor skipped"
    newest = {entry: revision for revision, entry, _ in got}
    assert newest == {f"img{i}": last - entries + 1 + i for i in range(entries)}
    assert len(got) < entries * rounds // 2, "it should have skipped most while it did not read"


def _varint(n: int) -> bytes:
    out = b""
    while True:
        low, n = n & 0x7F, n >> 7
        if not n:
            return out + bytes([low])
        out += bytes([low | 0x80])
