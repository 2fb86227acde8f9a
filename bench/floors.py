"""The floors: raw loopback TCP ping-pong, bare grpcio unary echo and bidi-stream ping-pong."""

from __future__ import annotations

import queue
import socket
import time
from typing import Any

import grpc

from bench.harness import PYTHON, latencies_us, rate, start, summary_us

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


def grpc_echo(n: int) -> dict[str, Any]:
    """Bare grpcio: sequential unary calls and ping-pong on one bidi stream."""
    server = start([PYTHON, "-m", "bench.servers", "grpc"])
    try:
        channel = grpc.insecure_channel(f"127.0.0.1:{server.first_line}")
        unary = channel.unary_unary("/bench.Echo/Unary", None, None)
        calls = rate(n, lambda i: unary(PAYLOAD, timeout=10))

        def rtt(_: int) -> float:
            t0 = time.perf_counter()
            unary(PAYLOAD, timeout=10)
            return time.perf_counter() - t0

        unary_lat = summary_us(latencies_us(n, rtt))

        def spaced_rtt(_: int) -> float:
            time.sleep(GAP_S)
            return rtt(0)

        # The same round trip with the spacing M3 uses: an idle pause before each call
        # costs wake-ups that back-to-back calls do not pay, so M3 is compared with this.
        spaced_lat = summary_us(latencies_us(n, spaced_rtt))
        requests: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        stream = channel.stream_stream("/bench.Echo/Stream", None, None)(iter(requests.get, None))
        responses = iter(stream)

        def ping(_: int) -> float:
            t0 = time.perf_counter()
            requests.put(PAYLOAD)
            next(responses)
            return time.perf_counter() - t0

        stream_lat = summary_us(latencies_us(n, ping))
        requests.put(None)
        channel.close()
        return {
            "unary_calls_per_s": round(calls),
            "unary": unary_lat,
            "unary_spaced": spaced_lat,
            "stream_ping_pong": stream_lat,
        }
    finally:
        server.stop()
