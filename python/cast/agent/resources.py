"""CPU and memory use of a process, read from Linux's /proc (no extra dependency).

CPU is the share of one core used since the previous sample of the same pid;
RSS is the resident set size. Elsewhere than Linux, or for a pid that is gone,
there is no sample.
"""

from __future__ import annotations

import os
import time

__all__ = ["ResourceMeter"]

_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def _cpu_seconds(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            raw = f.read()
    except OSError:
        return None
    # The command name (field 2) may hold spaces and parentheses: split after its last ')'.
    fields = raw[raw.rfind(b")") + 2:].split()
    try:
        return (int(fields[11]) + int(fields[12])) / _TICKS  # utime, stime (fields 14 and 15)
    except (IndexError, ValueError):
        return None


def _rss_bytes(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/statm", "rb") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, IndexError, ValueError):
        return None


class ResourceMeter:
    """Samples processes; remembers each pid's previous CPU time to give a percentage."""

    def __init__(self) -> None:
        self._last: dict[int, tuple[float, float]] = {}  # pid -> (monotonic time, cpu seconds)

    def sample(self, pid: int) -> tuple[float, int] | None:
        """(CPU % since the last sample of ``pid``, RSS bytes), or None if the process cannot be read."""
        cpu, rss = _cpu_seconds(pid), _rss_bytes(pid)
        if cpu is None or rss is None:
            self._last.pop(pid, None)
            return None
        now = time.monotonic()
        previous = self._last.get(pid)
        self._last[pid] = (now, cpu)
        if previous is None or now <= previous[0]:
            return 0.0, rss
        return 100.0 * (cpu - previous[1]) / (now - previous[0]), rss

    def forget(self, pid: int) -> None:
        """Drop what is remembered of ``pid`` (it exited)."""
        self._last.pop(pid, None)
