"""One publisher, subscriber processes: the harness the peers (Zenoh for M3 and M8, iceoryx2 for M8) share.

The publisher runs in the benchmark's process and stamps CLOCK_MONOTONIC just
before each put; each subscriber is a process of its own (as CAST's watchers
are) that stamps on arrival. A message is an 8-byte sequence number followed
by padding to the value's size. Before measuring, the publisher sends small
WARM messages until every subscriber has said ``ready`` (it has the route);
an END message makes each subscriber print one JSON line in the format of
CAST's watchers (bench/image_watcher.py), read with
:func:`bench.delivery_stats.parse_watcher`. Like CAST's watchers, a subscriber
reads every byte of each message (bench.checksum) before it stamps it.
"""

from __future__ import annotations

import json
import struct
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from bench import turns
from bench.checksum import MOD, word_sum
from bench.delivery_stats import parse_watcher
from bench.harness import ROOT, child_env

__all__ = ["END", "SETTLE_S", "WARM", "Receiver", "Subscribers", "drive", "frame"]

WARM = 2**64 - 1
END = 2**64 - 2
_SEQ = struct.Struct("<Q")


def frame(seq: int, size: int) -> bytes:
    """A message: the sequence number, padded to ``size`` bytes (at least the 8 of the number)."""
    return _SEQ.pack(seq) + b"p" * max(0, size - _SEQ.size)


class Receiver:
    """The subscriber's side: stamps each message, says ``ready`` at the first WARM, reports at END.

    With ``read_all`` (M8's large values) it reads every byte of each message
    first (a checksum, bench.checksum), as CAST's image watchers do; M3's small
    messages are stamped on arrival, as CAST's latency watcher does.
    """

    def __init__(self, read_all: bool = False) -> None:
        self.read_all = read_all
        self.stamps: dict[int, int] = {}
        self.bytes = 0
        self.checksum = 0
        self.ready = False
        self.done = threading.Event()

    def on_message(self, payload: bytes | memoryview) -> None:
        """One message as the peer's client library handed it over (bytes, or a view of its shared memory)."""
        (seq,) = _SEQ.unpack_from(payload)
        if seq == WARM:
            if not self.ready:
                self.ready = True
                print("ready", flush=True)
        elif seq == END:
            self.done.set()
        else:
            checksum = word_sum(payload) if self.read_all else 0
            self.stamps[seq] = time.perf_counter_ns()
            self.bytes += len(payload)
            self.checksum = (self.checksum + checksum) % MOD

    def report(self) -> None:
        """Print what arrived (as CAST's watchers do)."""
        print(json.dumps({"stamps": self.stamps, "bytes": self.bytes, "events": len(self.stamps),
                          "checksum": self.checksum}), flush=True)


class Subscribers:
    """``count`` subscriber processes started from ``command`` (each gets its index as a last argument)."""

    def __init__(self, command: Sequence[str], count: int, env: dict[str, str] | None = None) -> None:
        self._logs = [tempfile.TemporaryFile("w+") for _ in range(count)]
        self.procs = [
            subprocess.Popen(
                [*command, str(i)], stdout=subprocess.PIPE, stderr=self._logs[i], text=True, cwd=ROOT,
                env=child_env(env or {}),
            )
            for i in range(count)
        ]

    def handshake(self, warm: Callable[[], object], timeout_s: float = 60) -> None:
        """Call ``warm()`` every 5 ms until every subscriber printed ``ready``."""
        stop = threading.Event()

        def keep_warming() -> None:
            while not stop.is_set():
                warm()
                time.sleep(0.005)

        thread = threading.Thread(target=keep_warming, daemon=True)
        thread.start()
        try:
            deadline = time.monotonic() + timeout_s
            for i, proc in enumerate(self.procs):
                assert proc.stdout is not None
                line = proc.stdout.readline().strip()
                if line != "ready" or time.monotonic() > deadline:
                    raise RuntimeError(f"subscriber {i} did not start: {line!r} {self._tail(i)}")
        finally:
            stop.set()
            thread.join()
        time.sleep(0.05)  # WARM messages still on their way arrive before the first measured one

    def results(self, timeout_s: float = 120) -> list[dict[str, Any]]:
        """Each subscriber's report (after END)."""
        out = []
        for i, proc in enumerate(self.procs):
            text, _ = proc.communicate(timeout=timeout_s)
            lines = [line for line in text.splitlines() if line.startswith("{")]
            if not lines:
                raise RuntimeError(f"subscriber {i} printed no result: {self._tail(i)}")
            out.append(parse_watcher(json.loads(lines[-1])))
        return out

    def _tail(self, i: int) -> str:
        self._logs[i].seek(0)
        return self._logs[i].read()[-800:]

    def close(self) -> None:
        """Kill what is still running."""
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in self._logs:
            log.close()


SETTLE_S = 0.3  # the pause after a back-to-back warm-up, as M8's C++ writer makes (cast_bench image-write)
# The warm-up goes in bursts of WARM_BURST with WARM_PAUSE_S between them: a quarter of what M8's history holds of
# the warm-up's values (1,024 of 64 KiB in 64 MiB), and time for the slowest watcher to take a burst, so that
# no watcher can fall a history's length behind the writer in a part that is not measured (one burst of 10,200
# could: docs/performance-m8.md, "A server the scheduler favours loses the watchers in the warm-up").
WARM_BURST = 256
WARM_PAUSE_S = 0.05


def drive(put: Callable[[bytes], object], frames: int, gap_s: float, size: int, warm: int = 0,
          warm_size: int = 0, cold: int = 0, turn: int = turns.NONE,
          go: Callable[[], object] | None = None) -> dict[int, int]:
    """Puts, each stamped (ns) just before it; their stamps by sequence number, in the order put.

    As M8's C++ writer (``cast_bench image-write``): ``cold`` puts paced as
    below (the subscribers' first seconds), ``warm`` of ``warm_size`` bytes back
    to back in bursts of WARM_BURST, each but the last followed by WARM_PAUSE_S,
    and a pause of SETTLE_S (the warm-up), then ``frames``, the i-th
    started at start + i * ``gap_s`` (0: back to back). The reader tells the
    parts apart by number. ``go`` is called between the warm-up and the
    ``frames`` (it may wait); with a ``turn`` (:mod:`bench.turns`) those are put
    in that turn's seconds only, the pace starting again at each.
    """
    sent: dict[int, int] = {}

    def paced(count: int, gap: float, size: int, turn: int = turns.NONE) -> None:
        pad = b"p" * max(0, size - _SEQ.size)
        start = time.perf_counter()
        step = 0  # puts since `start`
        for _ in range(count):
            if gap:
                delay = start + step * gap - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            if turn and turns.wait_for_turn(turn):
                start, step = time.perf_counter(), 0
            step += 1
            seq = len(sent)
            payload = _SEQ.pack(seq) + pad  # made before the stamp
            sent[seq] = time.perf_counter_ns()
            put(payload)

    paced(cold, gap_s, size)
    if warm:
        for left in range(warm, 0, -WARM_BURST):
            paced(min(WARM_BURST, left), 0.0, warm_size)
            if left > WARM_BURST:
                time.sleep(WARM_PAUSE_S)
        time.sleep(SETTLE_S)
    if go is not None:
        go()
    paced(frames, gap_s, size, turn)
    return sent
