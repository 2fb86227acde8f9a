"""M8: image-sized entries. A C++ writer overwrites a 1 MiB entry; four watchers receive it.

Watchers, each a process of its own: Python, C++, Java, Python
(bench/image_watcher.py, ``cast_bench image-watch``, ``cast.bench.Bench
image-watch``), all watching the entry with its value; the Python and Java
watchers decode it, the C++ one reads every byte of the image through its
``ValueView`` (a checksum; on the server's host the value is lent by shared
memory). The writer is ``cast_bench image-write`` (sequential overwrites,
staged in shared memory). Four phases per
run: ``queue`` and ``latest`` delivery, each at 30 Hz and back to back, each
with new watcher processes on one ``cast serve`` whose server RSS is sampled
throughout. Zenoh and Redis do the same (bench/zenoh_peer.py, bench/redis_peer.py:
a Python publisher, four Python subscribers) in the same run, and the raw gRPC
floor (a bare unary echo of 1 MiB, bench/floors.py) is measured before each
back-to-back phase.
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import psutil

from bench import redis_peer, zenoh_peer
from bench.cast_cases import Server
from bench.delivery_stats import parse_watcher, totals, watcher_figures
from bench.floors import EchoFloor
from bench.harness import PYTHON, ROOT
from bench.other_clients import cpp_command, java_command

__all__ = ["HISTORY_BYTES", "HZ", "SIZE", "WATCHERS", "run"]

SIZE = 1 << 20  # a VGA RGB image is 0.9 MiB
HZ = 30
SA = "images"
# M8's server keeps at most this many bytes of values in its history (limits.history_bytes): small
# enough that a run fills it, so the RSS bound is exercised; 64 frames of slack for a queue watcher.
HISTORY_BYTES = 64 << 20
WATCHERS = ("Python 1", "C++", "Java", "Python 2")
TIMEOUT_S = 300  # the writer's whole run
AFTER_WRITER_S = 60  # how long the watchers may take to finish once the writer is done


def _watcher_command(label: str, delivery: str) -> list[str] | str:
    if label.startswith("Python"):
        return [PYTHON, "-m", "bench.image_watcher", delivery]
    command = cpp_command() if label == "C++" else java_command()
    return command if isinstance(command, str) else [*command, "image-watch", delivery]


class RssSampler:
    """The largest RSS of a process, sampled every 20 ms on a thread until :meth:`stop`."""

    def __init__(self, pid: int) -> None:
        self._proc = psutil.Process(pid)
        self.peak: int = self._proc.memory_info().rss
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(0.02):
            self.peak = max(self.peak, self._proc.memory_info().rss)

    def stop(self) -> int:
        """Stop sampling; the peak in bytes."""
        self._stop.set()
        self._thread.join()
        return self.peak


class _Watchers:
    """The four watcher processes of one phase."""

    def __init__(self, server: Server, delivery: str, tag: str) -> None:
        self.labels: list[str] = []
        self.procs: list[subprocess.Popen[str]] = []
        self.logs: list[IO[str]] = []
        self.missing: dict[str, str] = {}
        for i, label in enumerate(WATCHERS):
            command = _watcher_command(label, delivery)
            if isinstance(command, str):
                self.missing[label] = command
                continue
            log: IO[str] = tempfile.TemporaryFile("w+")
            env = {**os.environ, **server.env(f"m8-{tag}-w{i}", SA)}
            self.procs.append(subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=log, text=True,
                                               cwd=ROOT))
            self.labels.append(label)
            self.logs.append(log)
        for label, proc, log in zip(self.labels, self.procs, self.logs, strict=True):
            assert proc.stdout is not None
            line = proc.stdout.readline().strip()
            if line != "ready":
                raise RuntimeError(f"{label} watcher did not start: {line!r} {_tail(log)}")

    def results(self) -> dict[str, dict[str, Any]]:
        out = {}
        for label, proc, log in zip(self.labels, self.procs, self.logs, strict=True):
            try:
                text, _ = proc.communicate(timeout=AFTER_WRITER_S)
            except subprocess.TimeoutExpired:
                raise RuntimeError(f"{label} watcher had not seen the end {AFTER_WRITER_S} s after the writer: "
                                   f"{_tail(log)}") from None
            lines = [line for line in text.splitlines() if line.startswith("{")]
            if proc.returncode != 0 or not lines:
                raise RuntimeError(f"{label} watcher exited {proc.returncode}: {_tail(log)}")
            out[label] = parse_watcher(json.loads(lines[-1]))
        return out

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in self.logs:
            log.close()


def _tail(log: IO[str]) -> str:
    log.seek(0)
    return log.read()[-800:]


def _write(server: Server, writer: list[str], frames: int, gap_s: float, tag: str) -> dict[int, int]:
    env = {**os.environ, **server.env(f"m8-{tag}-writer", SA)}
    out = subprocess.run([*writer, "image-write", str(SIZE), str(frames), str(round(gap_s * 1e6))], env=env,
                         capture_output=True, text=True, timeout=TIMEOUT_S)
    lines = [line for line in out.stdout.splitlines() if line.startswith("{")]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"the C++ writer exited {out.returncode}: {out.stderr[-800:]}")
    return {int(k): int(v) for k, v in json.loads(lines[-1]).items()}


def _figures(sent: dict[int, int], got: dict[str, dict[str, Any]], extra: int) -> dict[str, Any]:
    """Each watcher's figures (the first tenth, at most 30, of its latencies dropped as warm-up) and the total."""
    warm = min(30, len(sent) // 10)
    late = dict(sorted(sent.items())[warm:])
    per = {}
    for label, g in got.items():
        whole = watcher_figures(sent, g, extra)
        steady = watcher_figures(late, g, extra)
        per[label] = {**whole, "p50_us": steady["p50_us"], "p99_us": steady["p99_us"]}
    return {"watchers": per, "total": totals(sent, list(got.values())), "frames": len(sent)}


def cast_phase(server: Server, writer: list[str], delivery: str, frames: int, gap_s: float) -> dict[str, Any]:
    """One phase on CAST: new watchers, the C++ writer, the server's peak RSS meanwhile."""
    tag = f"{delivery}-{'b2b' if gap_s == 0 else 'hz'}"
    watchers = _Watchers(server, delivery, tag)
    try:
        sampler = RssSampler(server.proc.process.pid)
        try:
            sent = _write(server, writer, frames, gap_s, tag)
            got = watchers.results()
        finally:
            peak = sampler.stop()
    finally:
        watchers.close()
    return {**_figures(sent, got, extra=2), "server_rss_peak": peak, "missing": watchers.missing}


def _peer(fn: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    run = fn(*args)
    labels = [f"subscriber {i + 1}" for i in range(len(run["watchers"]))]
    return _figures(run["sent"], dict(zip(labels, run["watchers"], strict=True)), extra=0)


def run(workdir: Path, frames: int, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every phase of M8 (``frames`` writes each) and its peers and floor; raw results for bench/rows_scale.py."""
    writer = cpp_command()
    if isinstance(writer, str):
        return {"error": writer}
    gap = 1 / HZ
    server = Server(workdir / "cast", [SA], limits={"history_bytes": HISTORY_BYTES})
    echo = EchoFloor()
    out: dict[str, Any] = {"size": SIZE, "hz": HZ, "history_bytes": HISTORY_BYTES, "floor": []}
    try:
        out["server_rss_idle"] = server.rss_bytes()
        for delivery in ("queue", "latest"):
            for phase, gap_s in (("hz", gap), ("b2b", 0.0)):
                if gap_s == 0:
                    log("M8 floor: bare gRPC echo of 1 MiB")
                    out["floor"].append(echo.big_echo(max(20, frames // 2), SIZE))
                log(f"M8 CAST, {delivery} delivery, {'back to back' if gap_s == 0 else f'{HZ} Hz'}")
                try:
                    out[f"cast_{delivery}_{phase}"] = cast_phase(server, writer, delivery, frames, gap_s)
                except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
                    out[f"cast_{delivery}_{phase}"] = {"error": str(exc)}
        out["server_rss_end"] = server.rss_bytes()
    finally:
        echo.close()
        server.stop()
    for name, mod in (("zenoh", zenoh_peer), ("redis", redis_peer)):
        for phase, gap_s in (("hz", gap), ("b2b", 0.0)):
            log(f"M8 {name}, {'back to back' if gap_s == 0 else f'{HZ} Hz'}")
            try:
                if mod is redis_peer:
                    (workdir / f"redis-{phase}").mkdir(parents=True, exist_ok=True)
                    out[f"{name}_{phase}"] = _peer(redis_peer.large, workdir / f"redis-{phase}", frames, gap_s, SIZE)
                else:
                    out[f"{name}_{phase}"] = _peer(zenoh_peer.large, frames, gap_s, SIZE)
            except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
                out[f"{name}_{phase}"] = {"error": str(exc)}
    return out
