"""REC1: what recording costs, how fast a recorder goes, how closely a replay keeps time.

- **Overhead**: two `cast serve` processes side by side, each with the same watcher process (bench O1's
  sides, bench/metrics_overhead.py); one also has a `cast record` process attached. A writer on raw stubs
  takes blocks on each in turn; the figure is the rate with the recorder over the rate without.
- **Throughput**: a recorder in this process reads a history of changes already written (``--from-revision
  1``) into an MCAP file as fast as it can: changes/s and MB/s of values.
- **Replay timing**: changes written 20 ms apart are recorded, then replayed at ``--rate 1.0`` into a fresh
  server; a watcher there stamps each arrival. The figure is how far each replayed interval is from the
  recorded one (median and p95 of the absolute error, ms): a tolerance to read, not a test's assertion.

Run alone: ``python -m bench.recording [--quick]`` (also part of ``make bench``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from google.protobuf.wrappers_pb2 import Int64Value

import cast
from bench.cast_cases import SECRET, Server
from bench.harness import PYTHON, child_env, percentile, scratch
from bench.metrics_overhead import SA, WriterSide, alternating
from bench.rows import fig
from cast.client.credentials import TokenSource
from cast.core.records import Identity
from cast.recording.mcap_file import RecordingWriter
from cast.recording.recorder import Recorder, RecordOptions

__all__ = ["run"]

TARGET = 0.9
CAST = str(Path(PYTHON).parent / "cast")


def _recorder_process(endpoint: str, path: Path) -> subprocess.Popen[str]:
    """`cast record` attached to ``endpoint``, once it says it records."""
    env = child_env({"CAST_SECRET": SECRET, "CAST_RUNTIME_DIR": "/nonexistent"})
    proc = subprocess.Popen([CAST, "record", "-o", str(path), "--endpoint", endpoint], env=env, text=True,
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL)
    assert proc.stderr is not None
    line = proc.stderr.readline()
    if "recording" not in line:
        proc.kill()
        raise RuntimeError(f"cast record did not start: {line}")
    return proc


def overhead(work: Path, calls: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Sequential Overwrite rates with and without a recorder attached; the recorder's changes."""
    sides: dict[str, WriterSide] = {}
    recorder: subprocess.Popen[str] | None = None
    try:
        for name in ("recorded", "plain"):
            sides[name] = WriterSide(work / name, metrics=True)
        recorder = _recorder_process(sides["recorded"].server.endpoint, work / "overhead.mcap")
        block = 100
        alternating(sides, lambda s: s.overwrites(block), 3)  # warm-up
        log("REC1 sequential Overwrite, recorded and not, taking turns")
        seconds = alternating(sides, lambda s: s.overwrites(block), max(1, calls // block))
    finally:
        if recorder is not None:
            recorder.send_signal(2)
            recorder.wait(60)
        for side in sides.values():
            side.close()
    return {name: block / s for name, s in seconds.items()}


def throughput(work: Path, changes: int, log: Callable[[str], None]) -> dict[str, float]:
    """A recorder reading ``changes`` changes of history into a file: changes/s and MB/s of values."""
    server = Server(work / "thr", [SA], limits={"history_events": changes + 100})
    try:
        writer = server.component("thr-writer", SA)
        log(f"REC1 writing {changes:,} changes for the recorder to read")
        value = Int64Value(value=1)
        for i in range(changes):
            writer.add(f"e{i}", value)
        writer._cast_close()
        tokens = TokenSource(server.signer.issue(Identity("bench-record", "")))
        recorder = Recorder(server.endpoint, tokens, RecordOptions(from_revision=1))
        stop = threading.Event()

        def until_all() -> None:
            while recorder.stats.changes < changes and not stop.is_set():
                time.sleep(0.005)
            stop.set()

        recorder.start()
        path = work / "throughput.mcap"
        out = RecordingWriter(path, recorder.header())
        watcher = threading.Thread(target=until_all, daemon=True)
        t0 = time.perf_counter()
        watcher.start()
        recorder.run(out, stop, time.monotonic() + 300, lambda gap: None)
        elapsed = time.perf_counter() - t0
        recorder.close()
        out.finish(recorder.trailer())
        return {"changes_per_s": recorder.stats.changes / elapsed,
                "mb_per_s": recorder.stats.data_bytes / elapsed / 1e6, "file_bytes": path.stat().st_size}
    finally:
        server.stop()


def replay_timing(work: Path, count: int, gap_s: float, log: Callable[[str], None]) -> dict[str, float]:
    """Absolute error of replayed intervals against recorded ones, ms (median, p95)."""
    source = Server(work / "src", [SA])
    target = Server(work / "dst", [SA])
    env = child_env({"CAST_SECRET": SECRET, "CAST_RUNTIME_DIR": "/nonexistent"})
    try:
        path = work / "timing.mcap"
        recorder = _recorder_process(source.endpoint, path)
        writer = source.component("timing-writer", SA)
        log(f"REC1 recording {count} changes {gap_s * 1000:.0f} ms apart")
        for i in range(count):
            writer.add(f"t{i}", Int64Value(value=i))
            time.sleep(gap_s)
        writer._cast_close()
        time.sleep(0.5)
        recorder.send_signal(2)
        recorder.wait(60)
        arrivals: list[float] = []
        watcher = target.component("timing-watcher", SA)
        watcher.on_change(cast.local_type_filter(Int64Value), lambda change: arrivals.append(time.perf_counter()))
        log("REC1 replaying at --rate 1.0")
        subprocess.run([CAST, "replay", str(path), "--endpoint", target.endpoint, "--rate", "1.0"], env=env,
                       check=True, capture_output=True, timeout=120)
        deadline = time.monotonic() + 10
        while len(arrivals) < count and time.monotonic() < deadline:
            time.sleep(0.01)
        watcher._cast_close()
        replayed = [b - a for a, b in itertools.pairwise(arrivals)]
        errors_ms = [abs(r - gap_s) * 1000 for r in replayed]
        return {"median_ms": statistics.median(errors_ms), "p95_ms": percentile(errors_ms, 95),
                "received": float(len(arrivals))}
    finally:
        source.stop()
        target.stop()


def run(work: Path, calls: int, changes: int, log: Callable[[str], None] = print) -> dict[str, Any]:
    """The REC1 row."""
    rates = overhead(work / "overhead", calls, log)
    thr = throughput(work, changes, log)
    timing = replay_timing(work / "timing", 100, 0.02, log)
    ratio = round(rates["recorded"] / rates["plain"], 3)
    return {
        "id": "REC1",
        "what": "recording: a writer's rate with `cast record` attached over the same without; the "
        "recorder reading history into MCAP; `cast replay --rate 1.0` against the recorded intervals",
        "target": f">= {TARGET} x the writer's rate without a recorder",
        "figures": [
            fig("sequential Overwrite, recorded (calls/s)", round(rates["recorded"]), floor=round(rates["plain"])),
            fig("recorder throughput (changes/s)", round(thr["changes_per_s"])),
            fig("recorder throughput (MB/s of values)", round(thr["mb_per_s"], 2)),
            fig("replay --rate 1.0: interval error, median (ms)", round(timing["median_ms"], 2)),
            fig("replay --rate 1.0: interval error, p95 (ms)", round(timing["p95_ms"], 2)),
        ],
        "note": f"ratio recorded/plain {ratio}; replay intervals of 20 ms, {int(timing['received'])} of 100 "
        f"changes received; the throughput file: {thr['file_bytes']:,} bytes for {changes:,} changes",
        "ratios": {"overwrite_per_s": ratio},
        "met": ratio >= TARGET,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the REC1 row alone and print it."""
    parser = argparse.ArgumentParser(prog="bench.recording")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    with scratch("cast-bench-rec-") as work:
        row = run(work, 1000 if args.quick else 5000, 5000 if args.quick else 50_000)
    print(json.dumps(row, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
