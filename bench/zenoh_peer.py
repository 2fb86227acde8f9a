"""The second peer: Zenoh (the `eclipse-zenoh` package), peer mode over loopback only.

The publisher's session runs in the benchmark's process and listens on a free
loopback port; each subscriber is a process of its own
(``python -m bench.zenoh_peer sub PORT read-all|stamp INDEX``) whose session connects to it.
Multicast scouting and gossip are off and every endpoint is on 127.0.0.1, so
no Zenoh traffic leaves the machine. The publisher uses congestion control
BLOCK (a put waits rather than drops when a subscriber falls behind): every
message is delivered, as CAST's ``queue`` delivery does. Everything else is
Zenoh's default configuration.

Measured: put -> subscriber latency of 100-byte values spaced as M3's writes
(:func:`latency`), and M8's image-sized values to four subscribers at 30 Hz
and back to back (:func:`large`).
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable
from importlib.metadata import version
from typing import Any

import zenoh

from bench import turns
from bench.delivery_stats import watcher_figures
from bench.harness import PYTHON, free_port
from bench.peer_fanout import END, WARM, Receiver, Subscribers, drive, frame

__all__ = ["config", "large", "latency", "zenoh_version"]

KEY = "bench/cast/peer"


def zenoh_version() -> str:
    """The installed eclipse-zenoh release."""
    return version("eclipse-zenoh")


def config(listen: list[str], connect: list[str]) -> zenoh.Config:
    """A peer-mode session on loopback only: no multicast scouting, no gossip, the given endpoints."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    return c


class _Publisher:
    """The publishing session (listening on a free loopback port) and its subscriber processes."""

    def __init__(self, subscribers: int, read_all: bool = False) -> None:
        self.port = free_port()
        self.session = zenoh.open(config([f"tcp/127.0.0.1:{self.port}"], []))
        self.publisher = self.session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        mode = "read-all" if read_all else "stamp"
        self.subs = Subscribers([PYTHON, "-m", "bench.zenoh_peer", "sub", str(self.port), mode], subscribers)
        try:
            warm = frame(WARM, 16)
            self.subs.handshake(lambda: self.publisher.put(warm))
        except BaseException:
            self.close()
            raise

    def run(self, frames: int, gap_s: float, size: int, warm: int = 0, warm_size: int = 0, cold: int = 0,
            turn: int = turns.NONE, go: Callable[[], object] | None = None
            ) -> tuple[dict[int, int], list[dict[str, Any]]]:
        """Publish (as :func:`bench.peer_fanout.drive`), end, and collect every subscriber's report."""
        sent = drive(self.publisher.put, frames, gap_s, size, warm, warm_size, cold, turn, go)
        self.publisher.put(frame(END, 16))
        return sent, self.subs.results()

    def close(self) -> None:
        """Stop the subscribers and close the session."""
        self.subs.close()
        self.publisher.undeclare()  # type: ignore[no-untyped-call]
        self.session.close()  # type: ignore[no-untyped-call]


def latency(n: int, gap_s: float) -> dict[str, Any]:
    """Put -> subscriber latency of 100-byte values, ``gap_s`` apart (M3's spacing), one subscriber."""
    pub = _Publisher(1)
    try:
        sent, (got,) = pub.run(n + min(100, n), gap_s, 100)
    finally:
        pub.close()
    warm = min(100, n)  # as bench.harness.latencies_us: the first ones warm up
    sent = {k: v for k, v in sent.items() if k >= warm}
    figures = watcher_figures(sent, {**got, "events": got["events"] - warm})
    return {key: figures[key] for key in ("p50_us", "p99_us", "mean_us", "lost")}


def large(frames: int, gap_s: float, size: int, subscribers: int = 4, warm: int = 0,
          warm_size: int = 0, cold: int = 0, turn: int = turns.NONE,
          go: Callable[[], object] | None = None) -> dict[str, Any]:
    """M8's run for Zenoh: ``frames`` values of ``size`` bytes, ``gap_s`` apart (0: back to back).

    Before them ``cold`` paced values and ``warm`` of ``warm_size`` bytes back to back, as M8's writer
    sends (:func:`bench.peer_fanout.drive`, which also says what ``turn`` and ``go`` do). Each subscriber
    reads every byte of each value (a checksum) before it stamps it, as M8's watchers do.
    """
    pub = _Publisher(subscribers, read_all=True)
    try:
        sent, got = pub.run(frames, gap_s, size, warm, warm_size, cold, turn, go)
    finally:
        pub.close()
    return {"sent": sent, "watchers": got}


def _subscriber(port: int, read_all: bool) -> int:
    session = zenoh.open(config([], [f"tcp/127.0.0.1:{port}"]))
    receiver = Receiver(read_all)
    subscriber = session.declare_subscriber(KEY, lambda sample: receiver.on_message(sample.payload.to_bytes()))
    receiver.done.wait(300)
    receiver.report()
    subscriber.undeclare()  # type: ignore[no-untyped-call]
    session.close()  # type: ignore[no-untyped-call]
    sys.stdout.flush()
    os._exit(0)  # Zenoh's runtime threads are not joined at interpreter exit


if __name__ == "__main__" and sys.argv[1] == "sub":
    _subscriber(int(sys.argv[2]), sys.argv[3] == "read-all")
