"""The rows of one Python client's calls: M1 against both gRPC floors, pipelined adds (M1P), M3 against Zenoh.

Pure functions of one run's results (see bench/rows.py for the table and the other rows).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from bench.rows import fig

if TYPE_CHECKING:
    from bench.rows import Results

__all__ = ["M3_P99_US", "m1_row", "m1p_row", "m3_row"]

M1_UNARY = 1.3  # streamed Add/Overwrite against the bare unary echo's calls/s
M1_STREAM = 0.8  # ... and against the bare bidi-stream ping-pong's
M1_GET = 0.8  # Get is a unary call: judged against the unary echo alone
PIPELINED = 3.0  # 64 adds in flight against sequential Add
M3_P99_US = 2000
M3_ZENOH = 3.0


def m1_row(r: Results) -> dict[str, Any]:
    """M1: sequential calls from one Python client against the unary echo and the stream ping-pong."""
    unary, stream = r.unary_cps, float(r.echo["stream_calls_per_s"])
    figures, met = [], True
    for name, value in r.m1.items():
        figures.append(fig(f"{name} (calls/s) vs unary echo", value, floor=round(unary)))
        if name == "get_per_s":
            met = met and value >= M1_GET * unary
        else:
            figures.append(fig(f"{name} (calls/s) vs stream ping-pong", value, floor=round(stream)))
            met = met and value >= M1_UNARY * unary and value >= M1_STREAM * stream
    return {
        "id": "M1",
        "what": "sequential Add, Get, Overwrite from one Python client (calls/s); Add and Overwrite on the write "
        "stream, Get unary",
        "target": f">= {M1_UNARY} x bare grpcio unary echo calls/s and >= {M1_STREAM} x bare bidi-stream "
        f"ping-pong for Add and Overwrite; Get >= {M1_GET} x unary",
        "figures": figures,
        "note": "each block of ours follows a floor block, unary echo and stream ping-pong in turn; calls/s = "
        "1 / mean round trip over all blocks",
        "met": met,
    }


def m1p_row(p: dict[str, Any]) -> dict[str, Any]:
    """Pipelined adds: add_async with 64 in flight against sequential Add, blocks in turn."""
    return {
        "id": "M1P",
        "what": f"pipelined Add from one Python client: add_async with {p['in_flight']} in flight (calls/s)",
        "target": f">= {PIPELINED} x sequential Add (measured in blocks taken in turn with it)",
        "figures": [fig("pipelined Add (calls/s)", p["pipelined_per_s"], floor=p["sequential_per_s"])],
        "met": p["pipelined_per_s"] >= PIPELINED * p["sequential_per_s"],
    }


def m3_row(r: Results) -> dict[str, Any]:
    """M3: write -> event latency against the unary echo at the same spacing and Zenoh's put -> subscriber."""
    zen = r.zenoh
    figures = [
        fig("p50 (µs)", r.m3["p50_us"], floor=r.spaced_p50, peer=zen.get("p50_us")),
        fig("p99 (µs)", r.m3["p99_us"], peer=zen.get("p99_us")),
        fig("lost", r.m3["lost"]),
        fig("Redis SET -> keyspace notification p50 (µs), shown", r.redis_p50),
    ]
    met = (
        r.m3["p50_us"] <= r.spaced_p50
        and "p50_us" in zen
        and r.m3["p50_us"] <= M3_ZENOH * zen["p50_us"]
        and r.m3["p99_us"] <= M3_P99_US
        and r.m3["lost"] == 0
    )
    note = "peer: Zenoh put -> subscriber (peer mode over loopback, subscriber in its own process, same spacing)"
    if "error" in zen:
        note += f"; Zenoh failed: {zen['error']}"
    else:
        # The write now travels on the write stream: in and out, each half a bare stream ping-pong.
        stream_floor = float(r.echo["stream_ping_pong_p50_us"])
        if M3_ZENOH * zen["p50_us"] < stream_floor:
            note += (
                f"; {M3_ZENOH} x Zenoh's p50 is {M3_ZENOH * zen['p50_us']:.0f} µs, below a bare stream ping-pong "
                f"({stream_floor:.0f} µs back to back: half of one carries the write in on the write stream, half "
                "the event out on the watch stream), what any gRPC write -> event costs here before any work"
            )
    return {
        "id": "M3",
        "what": "write -> event latency, Python writer -> Python watcher (µs)",
        "target": f"p50 <= 1.0 x grpcio unary p50 (same 2 ms spacing) and <= {M3_ZENOH} x Zenoh put -> subscriber "
        f"p50; p99 <= {M3_P99_US} µs",
        "figures": figures,
        "note": note,
        "met": met,
    }
