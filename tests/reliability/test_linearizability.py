"""Linearizability under SIGKILL: every entry is a versioned register, checked by a real checker.

Four components read, overwrite and compare-and-set (``expected_version``)
three entries at random while `cast serve` with a durable journal is killed
with SIGKILL and restarted on the same data and port. Each operation is
recorded with its invocation and response times; a write whose answer was
lost (the server died, the connection broke) has an unknown outcome and may
or may not have taken effect. The history is checked per entry with the
Wing-Gong / Lowe search of ``tests/reliability/linearizability.py``, with the
refusals' details (the version a compare-and-set was told) checked like any
read. A negative control corrupts the real history in a way that is
illegal by construction and checks that the checker says so.

Short in `make test`; `make soak` (CAST_SOAK=1) runs it longer with more
kills. The seed is printed; ``CAST_LIN_SEED`` replays its choices (operation
mix, keys, kill times; thread timing is the machine's).
"""

from __future__ import annotations

import os
import random
import re
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
from google.protobuf.wrappers_pb2 import StringValue

import cast
from tests.conftest import ServerHandle
from tests.reliability.conftest import kill9, serve, write_config
from tests.reliability.figures import record, soak
from tests.reliability.linearizability import Op, check, dump_history

SA = "vision"
KEYS = ("k0", "k1", "k2")
CLIENTS = 4
_AT_VERSION = re.compile(r"is at version (\d+)")


class Worker:
    """One component doing random reads, overwrites and compare-and-sets; records its history."""

    def __init__(self, handle: ServerHandle, index: int, seed: int, stop: threading.Event) -> None:
        self.name = f"c{index}"
        self.component = handle.connect(self.name, SA)
        self.rng = random.Random(seed * 31 + index)
        self.stop = stop
        self.ops: list[Op] = []
        self.known: dict[str, int] = {}  # the last version this client saw per key
        self.count = 0
        self.thread = threading.Thread(target=self._run, name=self.name, daemon=True)

    def _run(self) -> None:
        while not self.stop.is_set():
            key = self.rng.choice(KEYS)
            roll = self.rng.random()
            if roll < 0.4:
                self._read(key)
            else:
                self._write(key, cas=roll >= 0.7)

    def _read(self, key: str) -> None:
        call = time.monotonic()
        try:
            entry = self.component.get_entry(key, StringValue)
        except cast.CastError:
            time.sleep(0.01)  # a read that failed observed nothing: left out of the history
            return
        ret = time.monotonic()
        self.known[key] = entry.version
        self.ops.append(Op(self.name, key, "read", None, None, call, ret, "ok", entry.value.value, entry.version))

    def _write(self, key: str, cas: bool) -> None:
        self.count += 1
        value = f"{self.name}-{self.count}"
        expected = self.known.get(key, 0) if cas else None
        kind = "cas" if cas else "write"
        call = time.monotonic()
        try:
            result = self.component.overwrite(key, StringValue(value=value), expected_version=expected)
        except cast.ConsistencyError as exc:
            ret = time.monotonic()
            found = _AT_VERSION.search(exc.message)
            assert found, f"a version conflict that does not say the version: {exc.message}"
            self.ops.append(Op(self.name, key, kind, value, expected, call, ret, "conflict", None, int(found[1])))
            self.known[key] = int(found[1])
            return
        except (cast.UnavailableError, cast.DeadlineExceededError, cast.InternalError):
            # No answer: it may or may not have been applied, at any time after the call.
            self.ops.append(Op(self.name, key, kind, value, expected, call, None, "unknown", None, None))
            time.sleep(0.01)
            return
        ret = time.monotonic()
        self.known[key] = result.version
        self.ops.append(Op(self.name, key, kind, value, expected, call, ret, "ok", None, result.version))


def _run_workload(tmp_path: Path, mode: str, seconds: float, kills: int, seed: int) -> tuple[list[Op], dict]:
    config = write_config(tmp_path / "system.yaml", {
        "system": "lin",
        "subarchitectures": {SA: {}},
        "persistence": {"path": "wm.db", "durability": mode},
    })
    rng = random.Random(seed)
    # A slow disk, as in the report this test comes from: the window between a write's commit in
    # memory and its durability is what a wrong design lets others look into.
    slow = {"CAST_FAILPOINT_JOURNAL_DELAY_MS": "5"}
    handle = serve(config, env=slow)
    setup = handle.connect("setup", SA)
    initial = {}
    for key in KEYS:
        setup.add(key, StringValue(value=f"init-{key}"))
        initial[key] = (f"init-{key}", 0)
    setup._cast_close()
    stop = threading.Event()
    workers = [Worker(handle, i, seed, stop) for i in range(CLIENTS)]
    for w in workers:
        w.thread.start()
    kill_times = sorted(rng.uniform(0.15, 0.85) * seconds for _ in range(kills))
    started = time.monotonic()
    try:
        for at in kill_times:
            time.sleep(max(0.0, started + at - time.monotonic()))
            kill9(handle)
            time.sleep(rng.uniform(0.05, 0.4))
            handle = serve(config, listen=handle.endpoint, env=slow)
        time.sleep(max(0.0, started + seconds - time.monotonic()))
    finally:
        stop.set()
        for w in workers:
            w.thread.join(30)
        for w in workers:
            w.component._cast_close()
        handle.stop()
    ops = [op for w in workers for op in w.ops]
    return ops, initial


def _stale_read(ops: list[Op]) -> tuple[int, Op] | None:
    """A read made illegal: told a version older than one a write had returned before the read began."""
    reads = [(i, op) for i, op in enumerate(ops) if op.kind == "read" and op.result == "ok"]
    writes = [op for op in ops if op.kind in ("write", "cas") and op.result == "ok"]
    for i, read in reversed(reads):
        done = [w for w in writes if w.key == read.key and w.ret is not None and w.ret < read.call]
        if not done:
            continue
        newest = max(w.out_version or 0 for w in done)
        older = [r for _, r in reads if r.key == read.key and (r.out_version or 0) < newest]
        if older:
            stale = older[0]
            return i, replace(read, out_value=stale.out_value, out_version=stale.out_version)
    return None


@pytest.mark.parametrize("mode", ["always", "batch"])
def test_concurrent_reads_writes_and_compare_and_sets_under_sigkill_are_linearizable(
    tmp_path: Path, mode: str
) -> None:
    seed = int(os.environ.get("CAST_LIN_SEED") or random.SystemRandom().randrange(1 << 32))
    seconds, kills = (30.0, 6) if soak() else (6.0, 2)
    print(f"linearizability {mode}: seed {seed} (CAST_LIN_SEED={seed} replays), {seconds} s, {kills} kills")
    ops, initial = _run_workload(tmp_path, mode, seconds, kills, seed)
    result = check(ops, initial)
    unknown = sum(op.result == "unknown" for op in ops)
    figures = {"seed": seed, "operations": len(ops), "unknown_outcome": unknown, "kills": kills,
               "seconds": seconds, "by_kind": {k: sum(op.kind == k for op in ops) for k in ("read", "write", "cas")},
               "cas_conflicts": sum(op.result == "conflict" for op in ops)}
    print(figures)
    record(f"linearizability_{mode}", figures)
    history = tmp_path / "history.jsonl"
    dump_history(ops, history)
    assert result.ok is True, f"seed {seed}: history {history} is not linearizable:\n{result.report()}"
    # Enough happened for the check to mean something: every kind of call, and every key.
    assert figures["by_kind"]["read"] and figures["by_kind"]["write"] and figures["by_kind"]["cas"]
    assert {op.key for op in ops} == set(KEYS)

    # Negative control: the same history with one read made stale must be refused.
    corrupted = _stale_read(ops)
    assert corrupted is not None, "no read to corrupt: the workload did too little"
    index, bad = corrupted
    assert check([*ops[:index], bad, *ops[index + 1:]], initial).ok is False
