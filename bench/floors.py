"""The floors: raw loopback TCP ping-pong, bare grpcio unary echo and bidi-stream ping-pong."""

from __future__ import annotations

import queue
import socket
import time
from typing import Any

import grpc

from bench.harness import PYTHON, latencies_us, start, summary_us

PAYLOAD = b"x" * 150  # about the size of a small Add request
GAP_S = 0.002  # spacing of M3's writes (bench/cast_cases.py)


def tcp(n: int) -> dict[str, Any]:
    """Round trips over a raw TCP socket from Python."""
    server = start([PYTHON, "-m", "bench.servers", "tcp"])
    try:
        sock = socket.create_connection(("127.0.0.1", int(server.first_line)))
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        def once(_: int) -> float:
            t0 = time.perf_counter()
            sock.sendall(PAYLOAD)
            got = 0
            while got < len(PAYLOAD):
                got += len(sock.recv(65536))
            return time.perf_counter() - t0

        samples = latencies_us(n, once)
        sock.close()
        return {"round_trips_per_s": round(1e6 / (sum(samples) / len(samples))), **summary_us(samples)}
    finally:
        server.stop()


class EchoFloor:
    """A bare grpcio echo server and a client of it, kept up so floor calls can interleave with ours."""

    def __init__(self) -> None:
        self._server = start([PYTHON, "-m", "bench.servers", "grpc"])
        self._channel = grpc.insecure_channel(f"127.0.0.1:{self._server.first_line}")
        self._unary = self._channel.unary_unary("/bench.Echo/Unary", None, None)
        for _ in range(200):  # warm-up: connection, allocator, caches
            self.call()

    def call(self) -> None:
        """One unary echo round trip."""
        self._unary(PAYLOAD, timeout=10)

    def block_seconds(self, calls: int) -> float:
        """Seconds taken by ``calls`` back-to-back unary echo calls."""
        t0 = time.perf_counter()
        for _ in range(calls):
            self._unary(PAYLOAD, timeout=10)
        return time.perf_counter() - t0

    def latencies(self, n: int) -> dict[str, Any]:
        """Unary round trips back to back and spaced by M3's gap, and bidi-stream ping-pong."""

        def rtt(_: int) -> float:
            t0 = time.perf_counter()
            self._unary(PAYLOAD, timeout=10)
            return time.perf_counter() - t0

        unary_lat = summary_us(latencies_us(n, rtt))

        def spaced_rtt(_: int) -> float:
            time.sleep(GAP_S)
            return rtt(0)

        # The same round trip with the spacing M3 uses: an idle pause before each call
        # costs wake-ups that back-to-back calls do not pay, so M3 is compared with this.
        spaced_lat = summary_us(latencies_us(n, spaced_rtt))
        requests: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        stream = self._channel.stream_stream("/bench.Echo/Stream", None, None)(iter(requests.get, None))
        responses = iter(stream)

        def ping(_: int) -> float:
            t0 = time.perf_counter()
            requests.put(PAYLOAD)
            next(responses)
            return time.perf_counter() - t0

        stream_lat = summary_us(latencies_us(n, ping))
        requests.put(None)
        return {"unary": unary_lat, "unary_spaced": spaced_lat, "stream_ping_pong": stream_lat}

    def close(self) -> None:
        """Stop the echo server."""
        self._channel.close()
        self._server.stop()
