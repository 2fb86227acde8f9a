"""Timing helpers and subprocess servers shared by every benchmark."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PYTHON = sys.executable


def child_env(extra: Mapping[str, str]) -> dict[str, str]:
    """The environment of a process the benchmark starts: this one's plus ``extra`` (launch contract, secret).

    Nothing is put in front of a Python child's import path: it runs the same
    interpreter, so it imports the same ``cast`` package as the benchmark (the
    compiled wheel of ``.venv-mypyc`` under ``make bench``, the editable tree
    under ``.venv``), the build the report's header names.
    """
    return {**os.environ, **extra}


def free_port() -> int:
    """A free loopback port (for servers that cannot bind port 0 themselves, like redis-server)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def scratch(prefix: str) -> Iterator[Path]:
    """A working directory for one benchmark run: removed when the run ends, kept (and named) if it failed.

    The servers' configurations and logs go there; a failed run's are what
    one reads to see why, so only a run that ended normally removes them.
    """
    work = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        yield work
    except BaseException:
        print(f"the run's files are kept in {work}", file=sys.stderr, flush=True)
        raise
    shutil.rmtree(work, ignore_errors=True)


def percentile(samples: Sequence[float], q: float) -> float:
    """The q-th percentile (0..100) of samples, by nearest rank."""
    ordered = sorted(samples)
    if not ordered:
        return float("nan")
    k = max(0, min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1))))
    return ordered[k]


def rate(n: int, fn: Callable[[int], object]) -> float:
    """Calls per second of ``fn(i)``: a warm-up with i < 200, then n measured calls with the next i."""
    warm = min(200, n)
    for i in range(warm):
        fn(i)
    start = time.perf_counter()
    for i in range(warm, warm + n):
        fn(i)
    return n / (time.perf_counter() - start)


def latencies_us(n: int, fn: Callable[[int], float]) -> list[float]:
    """``fn(i)`` returns one latency in seconds; warm up (i < 100), then n samples in microseconds."""
    warm = min(100, n)
    for i in range(warm):
        fn(i)
    return [fn(i) * 1e6 for i in range(warm, warm + n)]


def summary_us(samples: Sequence[float]) -> dict[str, float]:
    """p50/p99/mean of latency samples (microseconds)."""
    return {
        "p50_us": round(percentile(samples, 50), 1),
        "p99_us": round(percentile(samples, 99), 1),
        "mean_us": round(statistics.fmean(samples), 1),
    }


@dataclass
class Proc:
    """A started helper process and the first line it printed."""

    process: subprocess.Popen[str]
    first_line: str

    def stop(self) -> None:
        """Terminate and reap."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def start(cmd: Sequence[str], cwd: Path | None = None, env: dict[str, str] | None = None) -> Proc:
    """Start a process and wait for its first line of output (its address)."""
    proc = subprocess.Popen(
        list(cmd),
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        cwd=cwd,
        env=child_env(env or {}),
    )
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    if not line:
        proc.kill()
        raise RuntimeError(f"{cmd[0]} did not start")
    return Proc(proc, line)
