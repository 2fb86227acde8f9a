"""bench.durability.one_cpu: every thread of the given processes and of this one on one CPU, then back."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from collections.abc import Iterator

import pytest

from bench.durability import one_cpu

CHILD = """
import threading, time, sys
for _ in range(3):
    threading.Thread(target=time.sleep, args=(60,), daemon=True).start()
print("ready", flush=True)
sys.stdin.read()
"""


def _cpus(pid: int) -> dict[int, set[int]]:
    return {int(t): os.sched_getaffinity(int(t)) for t in os.listdir(f"/proc/{pid}/task")}


@pytest.fixture
def child() -> Iterator[subprocess.Popen[str]]:
    proc = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    yield proc
    proc.kill()
    proc.wait()


def test_every_thread_of_the_processes_and_of_this_one_runs_on_one_cpu_then_as_before(
    child: subprocess.Popen[str],
) -> None:
    own = os.sched_getaffinity(0)
    if len(own) < 2:
        pytest.skip(f"this process may use one CPU only ({own}): nothing to pin")
    stop = threading.Event()
    helper = threading.Thread(target=stop.wait)  # a thread of this process, started before
    helper.start()
    try:
        before = {**_cpus(child.pid), **_cpus(os.getpid())}
        assert len(_cpus(child.pid)) >= 4 and all(len(c) >= 2 for c in before.values())
        with one_cpu([child.pid]):
            late = threading.Thread(target=stop.wait)  # started meanwhile: inherits the one CPU
            late.start()
            inside = {**_cpus(child.pid), **_cpus(os.getpid())}
            assert all(c == {min(own)} for c in inside.values()), inside
        after = {**_cpus(child.pid), **_cpus(os.getpid())}
        assert {t: after[t] for t in before} == before
        assert after[late.native_id] == os.sched_getaffinity(os.getpid())  # its process's first thread's
    finally:
        stop.set()
        helper.join()
