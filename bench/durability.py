"""D1: what durability costs: M1, M2 and M3 against one server per mode, in one run.

Four `cast serve` processes run side by side, memory only and with a journal
in `none`, `batch` and `always`. The modes take turns in blocks (block order
rotating), so a change in the machine's speed hits all of them alike; each
figure is then reported as a ratio to memory only, measured the same way.

What the figures show: in `always` and `batch` a write is answered once its
transaction is durable (an fsync), and becomes visible only then; reads
never wait for the journal, so Get should cost the same in every mode.

The sequential calls run with every thread of the four servers and of this
process on one CPU (:func:`one_cpu`): unpinned, where the scheduler happens to
place five processes on two vCPUs moved one mode's Get rate against another's
by +-15 % from run to run, more than the effect judged (docs/performance.md,
"D1: what durability costs").
"""

from __future__ import annotations

import itertools
import os
import statistics
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from google.protobuf.wrappers_pb2 import BytesValue

from bench.cast_cases import VALUE, Server, m3_latency

__all__ = ["MODES", "one_cpu", "run"]

MODES = ("memory", "none", "batch", "always")
_BLOCK = 100


def _servers(work: Path) -> dict[str, Server]:
    servers: dict[str, Server] = {}
    try:
        for mode in MODES:
            persistence = None if mode == "memory" else {"path": "wm.db", "durability": mode}
            servers[mode] = Server(work / mode, ["bench"], persistence=persistence)
    except BaseException:
        for server in servers.values():
            server.stop()
        raise
    return servers


def _threads(pid: int) -> list[int]:
    try:
        return [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except FileNotFoundError:  # the process ended
        return []


def _set_affinity(tid: int, cpus: set[int]) -> None:
    try:
        os.sched_setaffinity(tid, cpus)
    except (ProcessLookupError, PermissionError):  # a thread that ended meanwhile
        pass


@contextmanager
def one_cpu(pids: Sequence[int]) -> Iterator[None]:
    """Every thread of ``pids`` and of this process on one CPU meanwhile (the first this process may use).

    Then each thread gets back the CPUs it had; a thread started meanwhile
    (it inherited the one CPU) gets its process's first thread's.
    """
    own = os.sched_getaffinity(0)
    cpu = min(own)
    saved: dict[tuple[int, int], set[int]] = {}
    procs = [os.getpid(), *pids]
    for pid in procs:
        for tid in _threads(pid):
            try:
                saved[(pid, tid)] = os.sched_getaffinity(tid)
            except ProcessLookupError:
                continue
            _set_affinity(tid, {cpu})
    try:
        yield
    finally:
        for pid in procs:
            first = saved.get((pid, pid), own)
            for tid in _threads(pid):
                _set_affinity(tid, saved.get((pid, tid), first))


def _sequential(servers: dict[str, Server], n: int) -> dict[str, dict[str, float]]:
    """Add, Get, Overwrite calls/s per mode, in blocks of 100 taking turns: the median over the blocks.

    The median rather than all calls over all their time: a block of Gets on a
    session's socket lasts a few milliseconds, so a single stall of the machine
    in one block would otherwise move a mode's figure by a fifth. The blocks
    run on one CPU (:func:`one_cpu`), every mode's alike.
    """
    clients = {mode: server.component(f"d1-{mode}", "bench") for mode, server in servers.items()}
    pids = [server.proc.process.pid for server in servers.values()]
    rates: dict[str, dict[str, list[float]]] = {mode: {op: [] for op in ("add", "get", "overwrite")} for mode in MODES}
    ids = [f"d1-{i}" for i in range(n + _BLOCK)]
    try:
        for c in clients.values():  # warm-up: connection, schema registration, the journal's first pages
            for entry_id in ids[n:]:
                c.add(entry_id, VALUE)
                c.get(entry_id, BytesValue)
                c.overwrite(entry_id, VALUE)
        with one_cpu(pids):
            _blocks(clients, rates, ids, n)
    finally:
        for c in clients.values():
            c._cast_close()
    return {mode: {f"{op}_per_s": round(statistics.median(r)) for op, r in ops.items()} for mode, ops in rates.items()}


def _blocks(clients: dict[str, Any], rates: dict[str, dict[str, list[float]]], ids: list[str], n: int) -> None:
    """Add, Get and Overwrite in blocks of _BLOCK ids, each op's blocks taking turns by mode, the order rotating."""
    order = list(MODES)
    for start in range(0, n, _BLOCK):
        span = ids[start : min(n, start + _BLOCK)]
        order = order[1:] + order[:1]
        for op in ("add", "get", "overwrite"):
            for mode in order:
                rates[mode][op].append(len(span) / _timed(clients[mode], op, span))


def _timed(c: Any, op: str, span: list[str]) -> float:
    calls: dict[str, Callable[[str], object]] = {
        "add": lambda entry_id: c.add(entry_id, VALUE),
        "get": lambda entry_id: c.get(entry_id, BytesValue),
        "overwrite": lambda entry_id: c.overwrite(entry_id, VALUE),
    }
    fn = calls[op]
    t0 = time.perf_counter()
    for entry_id in span:
        fn(entry_id)
    return time.perf_counter() - t0


def _batches(servers: dict[str, Server], batches: int) -> dict[str, float]:
    """Entries/s of Batch calls of 100 adds per mode, ten batches per turn."""
    clients = {mode: server.component(f"d1b-{mode}", "bench") for mode, server in servers.items()}
    counter = itertools.count()
    seconds = dict.fromkeys(MODES, 0.0)
    try:
        for c in clients.values():
            c.batch([("add", f"d1w-{next(counter)}", VALUE) for _ in range(100)])
        order = list(MODES)
        for _ in range(0, batches, 10):
            order = order[1:] + order[:1]
            for mode in order:
                c = clients[mode]
                t0 = time.perf_counter()
                for _ in range(10):
                    c.batch([("add", f"d1b-{next(counter)}", VALUE) for _ in range(100)])
                seconds[mode] += time.perf_counter() - t0
    finally:
        for c in clients.values():
            c._cast_close()
    done = (batches // 10) * 10 * 100
    return {mode: round(done / s) for mode, s in seconds.items()}


def run(work: Path, n: int, batches: int, latency_samples: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Every D1 figure per mode: Add/Get/Overwrite calls/s, Batch entries/s, write -> event p50/p99."""
    servers = _servers(work)
    try:
        log("D1 sequential calls per durability mode")
        sequential = _sequential(servers, n)
        log("D1 batches per durability mode")
        batch = _batches(servers, batches)
        latency = {}
        for mode in MODES:
            log(f"D1 write -> event latency, {mode}")
            m3 = m3_latency(servers[mode], latency_samples)
            latency[mode] = {"p50_us": m3["p50_us"], "p99_us": m3["p99_us"], "lost": m3["lost"]}
    finally:
        for server in servers.values():
            server.stop()
    return {
        mode: {**sequential[mode], "batch_entries_per_s": batch[mode], **latency[mode]} for mode in MODES
    }
