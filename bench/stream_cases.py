"""M1 against both gRPC floors (unary echo and bidi-stream ping-pong), and pipelined adds.

A Python component's writes travel on one WorkingMemory.Write
stream (cast.client.write_stream), so sequential Add and Overwrite are compared
with the bare stream ping-pong as well as with the bare unary echo; Get stays a
unary call. Every block of ours follows a floor block, which floor alternating so
that each of our calls follows each floor equally often (see docs/performance.md,
Method: a block that follows one of our own runs slower than one after a pause).
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from google.protobuf.wrappers_pb2 import BytesValue

from bench.cast_cases import VALUE, Server
from bench.floors import EchoFloor

__all__ = ["m1_both_floors", "pipelined_adds", "window"]


def m1_both_floors(server: Server, echo: EchoFloor, n: int, block: int = 100, prefix: str = "m1") -> dict[str, Any]:
    """M1: sequential Add, Get, Overwrite from one client, each block after a floor block.

    In cycle k our j-th operation follows a unary echo block when j + k is
    even and a stream ping-pong block otherwise, so over two cycles each
    operation follows each floor once. Returns calls/s of ours and of both
    floors (``echo_per_s``: unary, ``stream_per_s``: ping-pong), each
    1 / mean round trip over all its blocks.
    """
    c = server.component(prefix, "bench")
    ids = [f"{prefix}-{i}" for i in range(n + block)]
    for i in range(block):  # warm-up: connection, write stream, schema registration
        c.add(ids[n + i], VALUE)
        c.get(ids[n + i], BytesValue)
        c.overwrite(ids[n + i], VALUE)
    ops: dict[str, Callable[[str], object]] = {
        "add": lambda entry_id: c.add(entry_id, VALUE),
        "get": lambda entry_id: c.get(entry_id, BytesValue),
        "overwrite": lambda entry_id: c.overwrite(entry_id, VALUE),
    }
    floors: dict[str, Callable[[int], float]] = {"echo": echo.block_seconds, "stream": echo.stream_block_seconds}
    seconds = dict.fromkeys([*floors, *ops], 0.0)
    calls = dict.fromkeys(seconds, 0)
    for k, start_i in enumerate(range(0, n, block)):
        span = ids[start_i : min(n, start_i + block)]
        for j, (name, op) in enumerate(ops.items()):
            floor = "echo" if (j + k) % 2 == 0 else "stream"
            seconds[floor] += floors[floor](len(span))
            calls[floor] += len(span)
            t0 = time.perf_counter()
            for entry_id in span:
                op(entry_id)
            seconds[name] += time.perf_counter() - t0
            calls[name] += len(span)
    c._cast_close()
    return {f"{k}_per_s": round(calls[k] / seconds[k]) for k in seconds}


def window(submit: Callable[[int], Future[Any]], count: int, in_flight: int) -> None:
    """``submit(i)`` for i in range(count), never more than ``in_flight`` futures unsettled; waits for all.

    Each future's result is taken, so an error raises here.
    """
    pending: collections.deque[Future[Any]] = collections.deque()
    for i in range(count):
        if len(pending) >= in_flight:
            pending.popleft().result(30)
        pending.append(submit(i))
    while pending:
        pending.popleft().result(30)


def pipelined_adds(server: Server, n: int, in_flight: int = 64, block: int = 100, ratio: int = 8) -> dict[str, Any]:
    """Adds with ``in_flight`` futures outstanding (``add_async``) against sequential adds, in turns.

    One component takes a block of ``block`` sequential adds, then a block of
    ``ratio * block`` pipelined ones, and so on until each side made about
    ``n`` timed calls (the pipelined side more, its blocks being longer so the
    window's fill and drain weigh little). Both from this process, on one write
    stream, so a change in the machine's speed hits both.
    """
    c = server.component("m1-async", "bench")
    counter = iter(range(10**9))

    def submit(_: int) -> Future[Any]:
        future: Future[Any] = c.add_async(f"a-{next(counter)}", VALUE)
        return future

    window(submit, 2 * in_flight * 4, in_flight)  # warm-up
    for _ in range(block):
        c.add(f"a-{next(counter)}", VALUE)
    seq_s = async_s = 0.0
    seq_n = async_n = 0
    while seq_n < n:
        ids = [f"a-{next(counter)}" for _ in range(block)]
        t0 = time.perf_counter()
        for entry_id in ids:
            c.add(entry_id, VALUE)
        seq_s += time.perf_counter() - t0
        seq_n += block
        t0 = time.perf_counter()
        window(submit, ratio * block, in_flight)
        async_s += time.perf_counter() - t0
        async_n += ratio * block
    c._cast_close()
    return {
        "in_flight": in_flight,
        "sequential_per_s": round(seq_n / seq_s),
        "pipelined_per_s": round(async_n / async_s),
    }
