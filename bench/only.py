"""`python -m bench.only M1|M3|M8|M9|M10 [--quick] [--out DIR]`: one row alone, with its floors or peers.

For working on one figure without the whole `make bench` (a few minutes) or
`make bench-quick`: the same code, the same floors measured in the same run,
the row printed as the table prints it and written to DIR/only-ID.md and .json
(bench/results/only/ by default). The full run is what the targets are judged on.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from bench import (
    floors,
    images,
    many_components,
    redis_peer,
    report,
    ros_bridge,
    rows_calls,
    rows_ros,
    rows_scale,
    stream_cases,
    zenoh_peer,
)
from bench.cast_cases import Server, m3_latency
from bench.harness import ROOT, scratch
from bench.rows import Results

__all__ = ["CHOICES", "main"]

CHOICES = ("M1", "M3", "M8", "M9", "M10")


def _results(echo: dict[str, Any], m1: dict[str, Any] | None = None, m3: dict[str, Any] | None = None,
             peer: dict[str, Any] | None = None, zenoh: dict[str, Any] | None = None) -> Results:
    empty: dict[str, Any] = {}
    return Results(empty, peer or empty, echo, m1 or empty, empty, m3 or empty, empty, empty, empty, empty, empty,
                   empty, empty, empty, zenoh=zenoh or empty)


def _m1(q: bool, work: Path) -> list[dict[str, Any]]:
    n = 500 if q else 3000
    server, echo = Server(work, ["bench"]), floors.EchoFloor()
    try:
        m1 = stream_cases.m1_both_floors(server, echo, n)
        m1p = stream_cases.pipelined_adds(server, n)
    finally:
        echo.close()
        server.stop()
    ech = {"unary_calls_per_s": m1.pop("echo_per_s"), "stream_calls_per_s": m1.pop("stream_per_s")}
    return [rows_calls.m1_row(_results(ech, m1=m1)), rows_calls.m1p_row(m1p)]


def _m3(q: bool, work: Path) -> list[dict[str, Any]]:
    n = 500 if q else 3000
    peer = redis_peer.run(n, work)
    zen = zenoh_peer.latency(n, floors.GAP_S)
    server, echo = Server(work / "cast", ["bench"]), floors.EchoFloor()
    try:
        lat = echo.latencies(n)
        m3 = m3_latency(server, n)
    finally:
        echo.close()
        server.stop()
    ech = {"unary_p50_us": lat["unary"]["p50_us"], "unary_spaced_p50_us": lat["unary_spaced"]["p50_us"],
           "stream_ping_pong_p50_us": lat["stream_ping_pong"]["p50_us"], "unary_calls_per_s": 0}
    return [rows_calls.m3_row(_results(ech, m3=m3, peer=peer, zenoh=zen))]


def _m8(q: bool, work: Path) -> list[dict[str, Any]]:
    return [rows_scale.m8_row(images.run(work, 60 if q else 300))]


def _m9(q: bool, work: Path, out: Path) -> list[dict[str, Any]]:
    m9 = many_components.run(work, [10, 100, 500], 100 if q else 1000)
    ok = {int(k): v for k, v in m9["counts"].items() if "error" not in v}
    ns = sorted(ok)
    if ns:
        report.plot_panels(out / "only-many_components.png", ns,
                           {"write -> event (µs)": {q: [ok[n][f"{q}_us"] for n in ns] for q in ("p50", "p99")},
                            "server CPU while writing (cores)": {"CPU": [ok[n]["busy_cpu"] for n in ns]}},
                           "component sessions", "M9", log_y=["write -> event (µs)"])
    return [rows_scale.m9_row(m9)]


def _m10(q: bool, work: Path) -> list[dict[str, Any]]:
    return [rows_ros.m10_row(ros_bridge.run(work, 90 if q else 150, lambda text: print(text, flush=True)))]


def main(argv: list[str] | None = None) -> int:
    """Run one row and print it."""
    parser = argparse.ArgumentParser(prog="bench.only")
    parser.add_argument("row", choices=CHOICES)
    parser.add_argument("--quick", action="store_true", help="the counts of make bench-quick")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "only")
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with scratch("cast-bench-only-") as work:
        if args.row == "M9":
            table = _m9(args.quick, work, out)
        else:
            table = {"M1": _m1, "M3": _m3, "M8": _m8, "M10": _m10}[args.row](args.quick, work)
    machine = report.machine_info({"seconds": round(time.time() - t0, 1)}, redis_peer.redis_server_version())
    command = f"python -m bench.only {args.row}{' --quick' if args.quick else ''}"
    report.write_markdown(out / f"only-{args.row}.md", table, machine, command)
    report.write_json(out / f"only-{args.row}.json", table, machine)
    print((out / f"only-{args.row}.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
