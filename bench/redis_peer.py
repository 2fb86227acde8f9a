"""The peer: Redis (Debian's redis-server) with keyspace notifications, driven by redis-py."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import redis

from bench.harness import PYTHON, free_port, latencies_us, rate, summary_us
from bench.peer_fanout import END, WARM, Receiver, Subscribers, drive, frame


def redis_server_version() -> str:
    """The version redis-server reports."""
    out = subprocess.run(["redis-server", "--version"], capture_output=True, text=True).stdout
    return next((w.split("=")[1] for w in out.split() if w.startswith("v=")), out.strip())


class RedisServer:
    """Debian's redis-server on a free loopback port, memory only, keyspace notifications on."""

    def __init__(self, workdir: Path, *extra: str) -> None:
        if shutil.which("redis-server") is None:
            raise RuntimeError("redis-server is not installed: `make bench` installs it with apt-get")
        self.port = free_port()
        self.proc = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--notify-keyspace-events", "KEA", "--dir", str(workdir), *extra],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.client = redis.Redis(port=self.port)
        for _ in range(100):
            try:
                self.client.ping()
                break
            except redis.ConnectionError:
                time.sleep(0.05)

    def stop(self) -> None:
        """Stop the server."""
        self.client.close()
        self.proc.terminate()
        self.proc.wait(10)


def run(n: int, workdir: Path) -> dict[str, Any]:
    """Sequential SET and GET, and SET -> keyspace notification latency."""
    server = RedisServer(workdir)
    try:
        client = server.client
        value = b"x" * 100
        sets = rate(n, lambda i: client.set(f"k{i}", value))
        gets = rate(n, lambda i: client.get(f"k{i}"))
        pubsub = client.pubsub()  # type: ignore[no-untyped-call]
        pubsub.psubscribe("__keyspace@0__:note")
        pubsub.get_message(timeout=1)  # the subscribe confirmation

        def notify(i: int) -> float:
            t0 = time.perf_counter()
            client.set("note", value)
            while True:
                msg = pubsub.get_message(timeout=1)
                if msg is not None and msg["type"] == "pmessage":
                    return time.perf_counter() - t0

        latency = summary_us(latencies_us(n, notify))
        pubsub.close()
        return {
            "set_ops_per_s": round(sets),
            "get_ops_per_s": round(gets),
            "notification": latency,
            "version": redis_server_version(),
        }
    finally:
        server.stop()


# M8 for Redis: one script call stores the value and publishes it (one round trip, the value sent once).
_SET_AND_PUBLISH = "redis.call('SET', KEYS[1], ARGV[1]); return redis.call('PUBLISH', KEYS[1], ARGV[1])"
_CHANNEL = "img"


def large(workdir: Path, frames: int, gap_s: float, size: int, subscribers: int = 4) -> dict[str, Any]:
    """M8's run for Redis: ``frames`` values of ``size`` bytes stored and published, ``gap_s`` apart (0: back to back).

    The writer runs a script that SETs the key and PUBLISHes the value on a
    channel each subscriber process reads (a keyspace notification carries no
    value, and a GET after it would add a round trip). Subscribers' output
    buffers are unbounded (``client-output-buffer-limit pubsub 0 0 0``): by
    default Redis disconnects a subscriber 32 MiB behind, while CAST's ``queue``
    delivery keeps every change its history holds.
    """
    server = RedisServer(workdir, "--client-output-buffer-limit", "pubsub 0 0 0")
    subs = Subscribers([PYTHON, "-m", "bench.redis_peer", "sub", str(server.port)], subscribers)
    try:
        script = server.client.register_script(_SET_AND_PUBLISH)
        warm = frame(WARM, 16)
        subs.handshake(lambda: server.client.publish(_CHANNEL, warm))
        sent = drive(lambda payload: script(keys=[_CHANNEL], args=[payload]), frames, gap_s, size)
        server.client.publish(_CHANNEL, frame(END, 16))
        return {"sent": sent, "watchers": subs.results()}
    finally:
        subs.close()
        server.stop()


def _subscriber(port: int) -> int:
    # RESP2: redis-py 8's RESP3 parser formats every pub/sub message into a debug log line (str() of
    # the whole value, 9 ms for 1 MiB here) whether or not the log is enabled.
    client = redis.Redis(port=port, protocol=2)
    pubsub = client.pubsub()  # type: ignore[no-untyped-call]
    pubsub.subscribe(_CHANNEL)
    receiver = Receiver()
    while not receiver.done.is_set():
        msg = pubsub.get_message(timeout=1)
        if msg is not None and msg["type"] == "message":
            receiver.on_message(msg["data"])
    receiver.report()
    pubsub.close()
    client.close()
    return 0


if __name__ == "__main__" and sys.argv[1] == "sub":
    sys.exit(_subscriber(int(sys.argv[2])))
