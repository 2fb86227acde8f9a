"""M9: many components. N sessions, each with heartbeats and one watch, while one writer adds at 100/s.

The sessions are opened by load-generator processes (bench/session_load.py, grpc.aio,
one channel per session), ``PROCESSES`` of them sharing the N sessions; the
writer is a Python component in this process adding a 100-byte BytesValue
every 10 ms (an absolute schedule), stamping CLOCK_MONOTONIC before each add.
For each N on one fresh ``cast serve``: the time from "go" to every session
registered with its watch created, the server's RSS per session (its RSS with
the sessions open minus before, over N), the server's CPU while the sessions
only beat and while the writer writes (a fraction of one core, and per
session), and every write -> event latency of every session.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil

from bench.cast_cases import VALUE, Server
from bench.harness import PYTHON, ROOT, summary_us
from cast.core.records import Identity

__all__ = ["PROCESSES", "WRITE_HZ", "run", "split"]

PROCESSES = 4
WRITE_HZ = 100
SA = "many"
IDLE_S = 1.0  # how long the server's CPU is measured with the sessions open and no writes


def split(count: int, parts: int) -> list[int]:
    """``count`` sessions shared by ``parts`` processes as evenly as possible (no empty share)."""
    return [n for n in (count // parts + (1 if i < count % parts else 0) for i in range(parts)) if n]


def _cpu_seconds(proc: psutil.Process) -> float:
    t = proc.cpu_times()
    return float(t.user + t.system)


class _Load:
    """The load-generator processes of one count."""

    def __init__(self, server: Server, count: int, workdir: Path) -> None:
        self.procs: list[subprocess.Popen[str]] = []
        for p, share in enumerate(split(count, PROCESSES)):
            ids = [f"m9-{count}-{p}-{i}" for i in range(share)]
            tokens = {cid: server.signer.issue(Identity(cid, SA)) for cid in ids}
            path = workdir / f"tokens-{count}-{p}.json"
            path.write_text(json.dumps(tokens))
            self.procs.append(subprocess.Popen(
                [PYTHON, "-m", "bench.session_load", server.endpoint, SA, str(path)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT,
            ))
        for proc in self.procs:
            self._expect(proc, "loaded")

    @staticmethod
    def _expect(proc: subprocess.Popen[str], word: str) -> None:
        assert proc.stdout is not None
        line = proc.stdout.readline().strip()
        if line != word:
            raise RuntimeError(f"an M9 load generator said {line!r}, not {word!r} (exit {proc.poll()})")

    def _say(self, line: str) -> None:
        for proc in self.procs:
            assert proc.stdin is not None
            proc.stdin.write(line + "\n")
            proc.stdin.flush()

    def open_all(self) -> float:
        """Seconds from "go" to every session registered and watching."""
        t0 = time.perf_counter()
        self._say("go")
        for proc in self.procs:
            self._expect(proc, "ready")
        return time.perf_counter() - t0

    def results(self, sent_file: Path) -> dict[str, Any]:
        self._say(f"stop {sent_file}")
        samples: list[float] = []
        lost = 0
        for proc in self.procs:
            out, _ = proc.communicate(timeout=120)
            doc = json.loads(out.strip().splitlines()[-1])
            samples += doc["samples_us"]
            lost += sum(doc["lost"])
        return {"samples": samples, "lost": lost}

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def one_count(workdir: Path, count: int, writes: int) -> dict[str, Any]:
    """M9 at ``count`` sessions on a fresh server."""
    server = Server(workdir / f"n{count}", [SA])
    load: _Load | None = None
    try:
        proc = psutil.Process(server.proc.process.pid)
        writer = server.component(f"m9-writer-{count}", SA)
        writer.add("warm", VALUE)  # the writer's stream and schema, before anything is measured
        rss_before = server.rss_bytes()
        load = _Load(server, count, workdir)
        register_s = load.open_all()
        time.sleep(0.5)
        rss_after = server.rss_bytes()
        cpu0, t0 = _cpu_seconds(proc), time.perf_counter()
        time.sleep(IDLE_S)
        idle_cpu = (_cpu_seconds(proc) - cpu0) / (time.perf_counter() - t0)
        sent: dict[int, int] = {}
        loads = [psutil.Process(p.pid) for p in load.procs]
        load0 = sum(_cpu_seconds(p) for p in loads)
        cpu0, start = _cpu_seconds(proc), time.perf_counter()
        for i in range(writes):
            delay = start + i / WRITE_HZ - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            t = time.perf_counter_ns()
            sent[writer.add(f"e{i}", VALUE).revision] = t
        busy_s = time.perf_counter() - start
        busy_cpu = (_cpu_seconds(proc) - cpu0) / busy_s
        load_cpu = (sum(_cpu_seconds(p) for p in loads) - load0) / busy_s
        sent_file = workdir / f"sent-{count}.json"
        sent_file.write_text(json.dumps(sent))
        got = load.results(sent_file)
        writer._cast_close()
    finally:
        if load is not None:
            load.close()
        server.stop()
    samples = got["samples"]
    return {
        "sessions": count,
        **(summary_us(samples) if samples else {"p50_us": float("nan"), "p99_us": float("nan")}),
        "lost": got["lost"],
        "events": len(samples),
        "register_s": round(register_s, 3),
        "rss_per_session_kib": round((rss_after - rss_before) / count / 1024, 1),
        "server_rss_mib": round(rss_after / 2**20, 1),
        "idle_cpu": round(idle_cpu, 3),
        "busy_cpu": round(busy_cpu, 3),
        "busy_cpu_per_session_pct": round(100 * busy_cpu / count, 3),
        "load_cpu": round(load_cpu, 3),
    }


def run(workdir: Path, counts: list[int], writes: int, log: Callable[[str], None] = print) -> dict[str, Any]:
    """M9 at each count; raw results for bench/rows_scale.py."""
    workdir.mkdir(parents=True, exist_ok=True)
    out = {}
    for count in counts:
        log(f"M9 {count} sessions in {len(split(count, PROCESSES))} processes, {writes} adds at {WRITE_HZ}/s")
        try:
            out[str(count)] = one_count(Path(tempfile.mkdtemp(dir=workdir)), count, writes)
        except (RuntimeError, OSError, subprocess.TimeoutExpired, json.JSONDecodeError) as exc:
            out[str(count)] = {"sessions": count, "error": str(exc)}
    return {"counts": out, "writes": writes, "processes": PROCESSES}
