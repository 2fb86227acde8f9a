"""O1: what the metrics cost: a writer's rate against a server that counts and one that does not.

Two `cast serve` processes run side by side, one as users run it (metrics on)
and one with ``--no-metrics``, each with a watcher process taking every event
with its value (so delivery, the costliest counting, is on the path). A writer on
raw stubs (the server's cost, not a client library's) takes blocks on each in
turn, the order alternating, so a change in the machine's speed hits both
alike; each figure is the rate with metrics over the rate without, measured the
same way in the same run. The in-process figure times the core alone
(``Access.write`` and handing the event to a watcher, no gRPC), where the
counting's own microseconds show.

Run alone: ``python -m bench.metrics_overhead [--quick]`` (also part of ``make bench``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc
from google.protobuf import any_pb2

from bench.cast_cases import VALUE, Server, m4_fanout
from bench.harness import PYTHON, child_env, scratch
from bench.rows import fig
from cast.core.access import Access, run_sync
from cast.core.records import BatchOp, Identity, Operation
from cast.core.system import System
from cast.core.watch import EventFilter, Subscription
from cast.v1 import entry_pb2, working_memory_pb2, working_memory_pb2_grpc

__all__ = ["SA", "WriterSide", "alternating", "blocks", "in_process_us", "run"]

SA = "ovh"
IDS = 100  # overwritten round robin, so the WM does not grow
BATCH = 100
TARGET = 0.95

WATCHER = r"""
import sys, threading, cast
from cast.client.runner import LaunchContract
from google.protobuf.wrappers_pb2 import BytesValue
c = cast.UnmanagedComponent()
c._cast_bind(LaunchContract.from_env().connect())
seen = [0]
def cb(ch):
    seen[0] += 1
c.on_change(cast.local_type_filter(BytesValue, include_entry=True), cb)
print("ready", flush=True)
sys.stdin.read()  # until the benchmark closes it
print(seen[0], flush=True)
"""


class WriterSide:
    """One `cast serve` (``metrics``: counting on, or ``--no-metrics``), its watcher process, a raw-stub writer."""

    def __init__(self, work: Path, metrics: bool) -> None:
        self.server = Server(work, [SA, "fanout"], serve_args=() if metrics else ("--no-metrics",))
        env = child_env(self.server.env("ovh-watcher", SA))
        self.watcher = subprocess.Popen([PYTHON, "-c", WATCHER], env=env, stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, text=True)
        assert self.watcher.stdout is not None
        if self.watcher.stdout.readline().strip() != "ready":
            self.watcher.kill()
            self.server.stop()
            raise RuntimeError("the O1 watcher process did not start")
        self.channel = grpc.insecure_channel(self.server.endpoint)
        self.stub = working_memory_pb2_grpc.WorkingMemoryStub(self.channel)
        token = self.server.signer.issue(Identity("ovh-writer", SA))
        self.md = (("authorization", f"Bearer {token}"),)
        value = any_pb2.Any()
        value.Pack(VALUE)
        addresses = [entry_pb2.EntryAddress(id=f"k{i}", subarchitecture=SA) for i in range(IDS)]
        for address in addresses:
            self.stub.Add(working_memory_pb2.AddRequest(address=address, value=value), metadata=self.md, timeout=30)
        self.single = [working_memory_pb2.OverwriteRequest(address=a, value=value) for a in addresses]
        self.gets = [working_memory_pb2.GetRequest(address=a) for a in addresses]
        self.batch = working_memory_pb2.BatchRequest(operations=[
            working_memory_pb2.BatchOperation(overwrite=self.single[i % IDS]) for i in range(BATCH)])

    def overwrites(self, n: int) -> float:
        """Seconds ``n`` sequential Overwrite calls took."""
        t0 = time.perf_counter()
        for i in range(n):
            self.stub.Overwrite(self.single[i % IDS], metadata=self.md, timeout=30)
        return time.perf_counter() - t0

    def reads(self, n: int) -> float:
        """Seconds ``n`` sequential Get calls took."""
        t0 = time.perf_counter()
        for i in range(n):
            self.stub.Get(self.gets[i % IDS], metadata=self.md, timeout=30)
        return time.perf_counter() - t0

    def batches(self, n: int) -> float:
        """Seconds ``n`` Batch calls of 100 overwrites took."""
        t0 = time.perf_counter()
        for _ in range(n):
            self.stub.Batch(self.batch, metadata=self.md, timeout=60)
        return time.perf_counter() - t0

    def close(self) -> int:
        """Stop everything; how many events the watcher received."""
        self.channel.close()
        out, _ = self.watcher.communicate("", timeout=60)
        self.server.stop()
        return int(out.strip().splitlines()[-1])


def blocks(sides: dict[str, Any], measure: Callable[[Any], float], count: int) -> dict[str, list[float]]:
    """Seconds of each of ``count`` blocks on each side, taking turns (who goes first alternates)."""
    seconds: dict[str, list[float]] = {name: [] for name in sides}
    order = list(sides)
    for _ in range(count):
        order.reverse()
        for name in order:
            seconds[name].append(measure(sides[name]))
    return seconds


def alternating(sides: dict[str, Any], measure: Callable[[Any], float], count: int) -> dict[str, float]:
    """Median seconds of a block on each side, over ``count`` blocks each, taking turns (:func:`blocks`).

    Medians, not sums: this machine is shared, and a burst of someone else's work
    lands in a few blocks of one side; the median of many short blocks ignores it.
    """
    return {name: statistics.median(times) for name, times in blocks(sides, measure, count).items()}


def in_process_us(writes: int, block: int = 500) -> dict[str, float]:
    """Microseconds per overwrite and event handed to a watcher, on the core alone, metrics on and off."""
    loops: dict[str, Callable[[int], float]] = {}
    for name in ("on", "off"):
        system = System("ovh", [SA], metrics=name == "on")
        writer, watcher = Access(system, Identity("w", SA)), Access(system, Identity("watcher", SA))
        sub = Subscription(system.host, lambda: None)
        watcher.watch(sub, 1, [EventFilter(subarchitecture=SA, include_entry=True)])
        data = VALUE.SerializeToString()
        ops = [BatchOp(Operation.OVERWRITE, SA, f"k{i}", "google.protobuf.BytesValue", data) for i in range(IDS)]
        for i in range(IDS):
            run_sync(system, writer.write(BatchOp(Operation.ADD, SA, f"k{i}", "google.protobuf.BytesValue", data)))

        def loop(n: int, system: System = system, writer: Access = writer, watcher: Access = watcher,
                 sub: Subscription = sub, ops: list[BatchOp] = ops) -> float:
            t0 = time.perf_counter()
            for i in range(n):
                run_sync(system, writer.write(ops[i % IDS]))
                watcher.take(sub)
            return time.perf_counter() - t0

        loop(block)  # warm-up
        loops[name] = loop
    median = alternating(loops, lambda loop: loop(block), max(1, writes // block))
    return {name: round(s / block * 1e6, 2) for name, s in median.items()}


def run(work: Path, calls: int, batches: int, fan_events: int, rounds: int = 3,
        log: Callable[[str], None] = print) -> dict[str, Any]:
    """The O1 row: sequential Overwrite, Batch and Get rates with metrics on, the rates with them off as floor.

    ``rounds`` times, two fresh servers (so that where the machine happens to run
    each process does not favour one side for the whole run), each taking blocks
    in turn. Rates are medians over every block of every round; the judged ratio
    is the median over pairs of neighbouring blocks (one on, one off) of their
    ratio. M4's fan-out (one writer, 16 watchers in 4 processes, ``fan_events``
    events) runs in the first round, in the order on, off, off, on (on, off with
    one round): shown, not judged (the target is the writer's).
    """
    block = 100
    times: dict[str, dict[str, list[float]]] = {kind: {"on": [], "off": []} for kind in ("seq", "bat", "get")}
    fan: dict[str, list[float]] = {"on": [], "off": []}
    events = {"on": 0, "off": 0}
    for r in range(rounds):
        sides: dict[str, WriterSide] = {}
        try:
            for name in ("on", "off") if r % 2 == 0 else ("off", "on"):
                sides[name] = WriterSide(work / f"{name}{r}", metrics=name == "on")
            log(f"O1 round {r + 1} of {rounds}: warm-up")
            alternating(sides, lambda s: s.overwrites(block) + s.batches(2) + s.reads(block), 3)
            log("O1 sequential Overwrite, metrics on and off taking turns")
            for name, got in blocks(sides, lambda s: s.overwrites(block), max(1, calls // block // rounds)).items():
                times["seq"][name] += got
            log("O1 Batch of 100 overwrites")
            for name, got in blocks(sides, lambda s: s.batches(2), max(1, batches // 2 // rounds)).items():
                times["bat"][name] += got
            log("O1 Get")
            for name, got in blocks(sides, lambda s: s.reads(block), max(1, calls // block // rounds)).items():
                times["get"][name] += got
            if r == 0:
                log("O1 fan-out to 16 watchers")
                for name in ("on", "off", "off", "on") if rounds > 1 else ("on", "off"):  # a quick run: once each
                    fan[name].append(m4_fanout(sides[name].server, fan_events)["delivered_per_s"])
        finally:
            for name, side in sides.items():
                events[name] += side.close()
    log("O1 in process (the core alone)")
    core = in_process_us(calls * 10)
    med = {kind: {name: statistics.median(t) for name, t in by.items()} for kind, by in times.items()}
    rate = {name: {"overwrite_per_s": round(block / med["seq"][name]),
                   "batch_entries_per_s": round(2 * BATCH / med["bat"][name]),
                   "get_per_s": round(block / med["get"][name])} for name in ("on", "off")}
    # Judged on the blocks in pairs (an "on" block and the "off" block next to it): the median of their
    # ratios, so that a slow spell of the machine, which hits both blocks of a pair, cancels out.
    keys = {"seq": "overwrite_per_s", "bat": "batch_entries_per_s", "get": "get_per_s"}
    ratios = {keys[kind]: round(statistics.median(off / on for on, off in zip(by["on"], by["off"], strict=True)), 3)
              for kind, by in times.items()}
    return {
        "id": "O1",
        "what": "a writer's rate against a server counting its metrics, the same with --no-metrics as "
        "the floor; a watcher process takes every event with its value",
        "target": f">= {TARGET} x the rate with --no-metrics (sequential Overwrite and Batch)",
        "figures": [
            fig("sequential Overwrite (calls/s)", rate["on"]["overwrite_per_s"], floor=rate["off"]["overwrite_per_s"]),
            fig("Batch of 100 overwrites (entries/s)", rate["on"]["batch_entries_per_s"],
                floor=rate["off"]["batch_entries_per_s"]),
            fig("Get (calls/s)", rate["on"]["get_per_s"], floor=rate["off"]["get_per_s"]),
            fig("fan-out: 16 watchers, delivered events/s (not judged)", round(statistics.median(fan["on"])),
                floor=round(statistics.median(fan["off"]))),
            fig("in process: overwrite + its event to a watcher (µs)", core["on"], floor=core["off"]),
        ],
        "note": f"rate on / rate off, the median over pairs of neighbouring blocks: Overwrite "
        f"{ratios['overwrite_per_s']}, Batch {ratios['batch_entries_per_s']}, Get {ratios['get_per_s']} (rates: "
        f"medians of {block}-call blocks, 2-batch blocks, over {rounds} rounds of fresh servers); on the core "
        f"alone counting adds {core['on'] - core['off']:.2f} µs to a write and its event; events received by the "
        f"watchers: {events['on']:,} (on), {events['off']:,} (off)",
        "ratios": ratios,
        "met": ratios["overwrite_per_s"] >= TARGET and ratios["batch_entries_per_s"] >= TARGET,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the O1 row alone and print it as JSON."""
    parser = argparse.ArgumentParser(prog="bench.metrics_overhead")
    parser.add_argument("--quick", action="store_true", help="smaller counts")
    args = parser.parse_args(argv)
    q = args.quick
    with scratch("cast-bench-o1-") as work:
        row = run(work, 600 if q else 6000, 120 if q else 1200, 1000 if q else 10_000, 1 if q else 3,
                  lambda msg: print(msg, file=sys.stderr, flush=True))
    print(json.dumps(row, indent=2, ensure_ascii=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
