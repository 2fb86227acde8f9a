"""The floors: raw loopback TCP ping-pong, bare grpcio unary echo and bidi-stream ping-pong."""

from __future__ import annotations

import queue
import socket
import time
from collections.abc import Iterator
from typing import Any

import grpc

from bench.harness import PYTHON, latencies_us, start, summary_us
from cast.server.app import MAX_MESSAGE_BYTES

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
        self._channel = grpc.insecure_channel(
            f"127.0.0.1:{self._server.first_line}",
            options=[("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
                     ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES)],
        )
        self._unary = self._channel.unary_unary("/bench.Echo/Unary", None, None)
        self._pings: queue.SimpleQueue[bytes | None] | None = None
        self._pongs: Iterator[bytes] | None = None
        for _ in range(200):  # warm-up: connection, allocator, caches
            self.call()

    def call(self) -> None:
        """One unary echo round trip."""
        self._unary(PAYLOAD, timeout=10)

    def stream_block_seconds(self, calls: int) -> float:
        """Seconds taken by ``calls`` back-to-back ping-pongs on one bidi stream, kept open between blocks.

        The request side is a queue read by gRPC's thread, as the CAST client's
        write stream sends (cast.client.write_stream): the bare form of its path.
        """
        if self._pongs is None:
            self._pings = queue.SimpleQueue()
            stream = self._channel.stream_stream("/bench.Echo/Stream", None, None)
            self._pongs = iter(stream(iter(self._pings.get, None)))
            for _ in range(200):
                self._pings.put(PAYLOAD)
                next(self._pongs)
        assert self._pings is not None
        put, pongs = self._pings.put, self._pongs
        t0 = time.perf_counter()
        for _ in range(calls):
            put(PAYLOAD)
            next(pongs)
        return time.perf_counter() - t0

    def big_echo(self, calls: int, size: int, gap_s: float = 0.0) -> dict[str, Any]:
        """Unary echo of ``size`` bytes: round trips (µs) and the payload rate one way (MB/s, 10**6 bytes).

        The raw gRPC floor of M8: one value in and the same value out per call,
        back to back (``gap_s`` 0) or spaced.
        """
        payload = b"x" * size

        def once(_: int) -> float:
            if gap_s:
                time.sleep(gap_s)
            t0 = time.perf_counter()
            self._unary(payload, timeout=30)
            return time.perf_counter() - t0

        for i in range(min(20, calls)):
            once(i)
        samples = [once(i) * 1e6 for i in range(calls)]
        mean_s = sum(samples) / len(samples) / 1e6
        return {**summary_us(samples), "mb_per_s": round(size / mean_s / 1e6, 1), "size": size}

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
        if self._pings is not None:
            self._pings.put(None)
        self._channel.close()
        self._server.stop()
