"""R1: writer throughput with a watcher that has stopped reading, against the same writes with none.

The target bounds the slowdown at 20% (docs/reliability.md). Rounds alternate (without, with, without,
with, ...) and medians are compared, so a passing load on the machine hits both
sides alike. Two write patterns: batches of 1,000 overwrites (the most events
per second a writer can make) and sequential single overwrites (the common case).
"""

from __future__ import annotations

import statistics
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import grpc
from google.protobuf import any_pb2
from google.protobuf.wrappers_pb2 import Int64Value

from bench.cast_cases import Server
from cast.core.records import Identity
from cast.v1 import entry_pb2, working_memory_pb2, working_memory_pb2_grpc

BATCH = 1000
IDS = 100  # writes overwrite these round-robin, so the WM itself does not grow
HISTORY = 20_000


def _address(i: int) -> entry_pb2.EntryAddress:
    return entry_pb2.EntryAddress(id=f"k{i % IDS}", subarchitecture="stall")


class _Writer:
    """Raw-stub writes, so the figure is the server's cost and not a client library's."""

    def __init__(self, stub: working_memory_pb2_grpc.WorkingMemoryStub, md: Any) -> None:
        self.stub, self.md = stub, md
        self.value = any_pb2.Any()
        self.value.Pack(Int64Value(value=7))
        ops = [
            working_memory_pb2.BatchOperation(
                overwrite=working_memory_pb2.OverwriteRequest(address=_address(i), value=self.value)
            )
            for i in range(BATCH)
        ]
        self.batch = working_memory_pb2.BatchRequest(operations=ops)
        self.single = [working_memory_pb2.OverwriteRequest(address=_address(i), value=self.value) for i in range(IDS)]

    def batches_per_s(self, events: int) -> float:
        """Events per second written as batches of overwrites."""
        began = time.perf_counter()
        for _ in range(events // BATCH):
            self.stub.Batch(self.batch, metadata=self.md, timeout=60)
        return (events // BATCH) * BATCH / (time.perf_counter() - began)

    def sequential_per_s(self, calls: int) -> float:
        """Overwrite calls per second, one at a time."""
        began = time.perf_counter()
        for i in range(calls):
            self.stub.Overwrite(self.single[i % IDS], metadata=self.md, timeout=60)
        return calls / (time.perf_counter() - began)


class _StalledWatcher:
    """A watch stream that reads its acknowledgement and then nothing more."""

    def __init__(self, stub: working_memory_pb2_grpc.WorkingMemoryStub, md: Any) -> None:
        self._release = threading.Event()
        self.stream = cast(Any, stub.Watch(self._requests(), metadata=md))  # its stub types are not iterable
        next(self.stream)  # WatchCreated; from here on the watcher reads nothing

    def _requests(self) -> Iterator[working_memory_pb2.WatchRequest]:
        yield working_memory_pb2.WatchRequest(
            create=working_memory_pb2.WatchCreate(
                watch_id=1, filters=[entry_pb2.ChangeFilter(subarchitecture="stall", include_entry=True)]
            )
        )
        self._release.wait()

    def close(self) -> None:
        """End the stream (the server drops the subscription)."""
        self._release.set()
        self.stream.cancel()


def run(workdir: Path, events: int, calls: int, rounds: int) -> dict[str, Any]:
    """Median writer rates with and without a stalled watcher, and their ratios."""
    server = Server(workdir, ["stall"], limits={"history_events": HISTORY})
    channel = grpc.insecure_channel(server.endpoint)
    try:
        stub = working_memory_pb2_grpc.WorkingMemoryStub(channel)
        md = (("authorization", f"Bearer {server.signer.issue(Identity('writer', 'stall'))}"),)
        watch_md = (("authorization", f"Bearer {server.signer.issue(Identity('stalled', 'stall'))}"),)
        writer = _Writer(stub, md)
        for i in range(IDS):
            stub.Add(working_memory_pb2.AddRequest(address=_address(i), value=writer.value), metadata=md)
        writer.batches_per_s(min(events, 20_000))  # warm-up
        writer.sequential_per_s(min(calls, 500))
        runs: dict[str, list[float]] = {"batch_without": [], "batch_with": [], "seq_without": [], "seq_with": []}
        for _ in range(rounds):
            runs["batch_without"].append(writer.batches_per_s(events))
            runs["seq_without"].append(writer.sequential_per_s(calls))
            watcher = _StalledWatcher(stub, watch_md)
            try:
                runs["batch_with"].append(writer.batches_per_s(events))
                runs["seq_with"].append(writer.sequential_per_s(calls))
            finally:
                watcher.close()
        med = {k: statistics.median(v) for k, v in runs.items()}
        return {
            "batch_events_per_s_without": round(med["batch_without"]),
            "batch_events_per_s_with": round(med["batch_with"]),
            "batch_ratio": round(med["batch_with"] / med["batch_without"], 3),
            "sequential_per_s_without": round(med["seq_without"]),
            "sequential_per_s_with": round(med["seq_with"]),
            "sequential_ratio": round(med["seq_with"] / med["seq_without"], 3),
            "events": events,
            "history_events": HISTORY,
        }
    finally:
        channel.close()
        server.stop()
