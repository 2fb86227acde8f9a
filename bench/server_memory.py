"""The server's memory while M8 runs: its private memory and the shared memory it holds, sampled on a thread."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Sequence

from bench import turns

__all__ = ["PRIVATE_EVERY_S", "QUIET_AT_NS", "SHARED_EVERY", "ServerMemory", "idle_memory", "shared_bytes"]

PRIVATE_EVERY_S = 0.1
"""How often :class:`ServerMemory` reads the server's private memory."""
SHARED_EVERY = 2
"""Every how many of those samples it reads the server's shared memory too (every 200 ms)."""
QUIET_AT_NS = 10_000_000
"""Between turns, it samples this far into each second: the last frame of the second before has been read, and
the next side writes from :data:`bench.turns.SKIP_NS` on."""


def _status_kib(pid: int, keys: Sequence[str]) -> int:
    with open(f"/proc/{pid}/status") as f:
        return sum(int(line.split()[1]) for line in f if line.split(":")[0] in keys)


def shared_bytes(pid: int) -> int:
    """The whole size of every memory file (memfd) or /dev/shm file process ``pid`` maps or holds open.

    Its shared memory: the arena's segments and the sessions' staging areas,
    each counted once (by inode) at its full size, touched or not.
    """
    sizes: dict[int, int] = {}
    with open(f"/proc/{pid}/maps") as f:
        text = f.read()
    for line in text.splitlines():
        # Most of a server's few hundred mappings are its libraries: skipped before they are split (splitting
        # them all was a sixth of a reading; the kernel writing out the file is most of the rest).
        if "/memfd:" not in line and "/dev/shm/" not in line:
            continue
        parts = line.split(maxsplit=5)
        if len(parts) == 6 and parts[5].startswith(("/memfd:", "/dev/shm/")):
            start, end = (int(x, 16) for x in parts[0].split("-"))
            inode = int(parts[4])
            sizes[inode] = max(sizes.get(inode, 0), end - start)
    fds = f"/proc/{pid}/fd"
    for fd in os.listdir(fds):
        try:
            if os.readlink(f"{fds}/{fd}").startswith(("/memfd:", "/dev/shm/")):
                st = os.stat(f"{fds}/{fd}")
                sizes[st.st_ino] = max(sizes.get(st.st_ino, 0), st.st_size)
        except OSError:  # closed meanwhile
            continue
    return sum(sizes.values())


class ServerMemory:
    """The server's memory, sampled on a thread until :meth:`stop`.

    The peak of its private resident memory (RssAnon + RssFile: its own
    mapping of its shared memory, RssShmem, is left out, not to count it twice)
    plus the whole size of the shared memory it holds (:func:`shared_bytes`),
    and the peaks of each. The private memory is read every
    :data:`PRIVATE_EVERY_S` (one small ``/proc`` file); the shared memory every
    :data:`SHARED_EVERY` samples and once more at the end, because reading a
    server's mappings and descriptors costs a few hundred µs of CPU, which a
    sampler must not take from the system it measures at every frame
    (docs/performance.md, "The memory bound"). The shared memory changes by
    whole arena segments, made when the others are full and retired by a pass
    once a second that keeps one spare while values come, so its steps outlast
    the 200 ms between those samples. With ``between_turns`` (M8's judged
    phase, :mod:`bench.turns`) it reads both once a second, :data:`QUIET_AT_NS`
    into the second, when neither CAST nor Zenoh writes: the sampler is the
    benchmark's instrument, and its CPU then meets no frame of either side.
    """

    def __init__(self, pid: int, between_turns: bool = False) -> None:
        self._pid = pid
        self._between_turns = between_turns
        self.peak = self.private = self.shared = 0
        self._last_shared = 0
        self._sample_once(True)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample_once(self, shared_too: bool) -> None:
        private = _status_kib(self._pid, ("RssAnon", "RssFile")) * 1024
        self.private = max(self.private, private)
        shared = shared_bytes(self._pid) if shared_too else self._last_shared
        self._last_shared = shared
        self.shared = max(self.shared, shared)
        self.peak = max(self.peak, private + shared)

    def _sample(self) -> None:
        count = 0
        while not self._stop.wait(self._until_next()):
            count += 1
            try:
                self._sample_once(self._between_turns or count % SHARED_EVERY == 0)
            except OSError:  # the server ended
                return

    def _until_next(self) -> float:
        """Seconds to the next sample: PRIVATE_EVERY_S, or to QUIET_AT_NS into the next second between turns."""
        if not self._between_turns:
            return PRIVATE_EVERY_S
        now = time.monotonic_ns()
        at = now // turns.SECOND_NS * turns.SECOND_NS + QUIET_AT_NS
        return ((at if at > now else at + turns.SECOND_NS) - now) / 1e9

    def stop(self) -> dict[str, int]:
        """Stop sampling, read both once more, and give the peaks in bytes."""
        self._stop.set()
        self._thread.join()
        try:
            self._sample_once(True)
        except OSError:  # the server ended
            pass
        return {"peak": self.peak, "private": self.private, "shared": self.shared}


def idle_memory(pid: int) -> int:
    """The server's private resident memory plus its shared memory, once."""
    return _status_kib(pid, ("RssAnon", "RssFile")) * 1024 + shared_bytes(pid)


