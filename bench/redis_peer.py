"""The peer: Redis (Debian's redis-server) with keyspace notifications, driven by redis-py."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import redis

from bench.harness import free_port, latencies_us, rate, summary_us


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
