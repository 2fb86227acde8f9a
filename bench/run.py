"""`python -m bench.run [--quick]`: floors, peers and CAST in one run; writes bench/results/."""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from bench import (
    cast_cases,
    durability,
    floors,
    iceoryx2_peer,
    images,
    many_components,
    metrics_overhead,
    other_clients,
    recording,
    redis_peer,
    report,
    ros_bridge,
    stalled_watcher,
    stream_cases,
    zenoh_peer,
)
from bench.harness import ROOT, scratch
from bench.rows import Results, rows

RESULTS = ROOT / "bench" / "results"


def main(argv: list[str] | None = None) -> int:
    """Run every benchmark and write the report."""
    parser = argparse.ArgumentParser(prog="bench.run")
    parser.add_argument("--quick", action="store_true", help="smaller counts (about three minutes)")
    parser.add_argument("--smoke", action="store_true",
                        help="the smallest counts, only to show every row runs (the test suite's; figures meaningless)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.time()

    def log(msg: str) -> None:
        print(f"[{time.time() - t_start:6.1f}s] {msg}", flush=True)

    scale = SMOKE if args.smoke else QUICK if args.quick else FULL
    with scratch("cast-bench-") as work:
        results, scaling, m7_samples = _measure(scale, work, log)
    command = "python -m bench.run --smoke" if args.smoke else "make bench-quick" if args.quick else "make bench"
    _write(out, results, command)
    _plot(out, results, scaling, m7_samples)
    log(f"wrote {out / 'latest.md'}")
    print((out / "latest.md").read_text())
    return 0


class Scale(NamedTuple):
    """How much each row measures: `make bench`, `make bench-quick`, or the test suite's smoke run."""

    quick: bool
    n: int
    rounds: int
    m2_batches: int
    fan_events: int
    m6_checkpoints: list[int]
    m6_probe: int
    r1_events: int
    r1_calls: int
    d1_batches: int
    jit_warm: int
    m8_frames: int
    m9_counts: list[int]
    m9_writes: int
    o1: tuple[int, int, int]
    rec1: tuple[int, int]
    m10_frames: int = 150


FULL = Scale(False, 3000, 3, 300, 10_000, [1000, 10_000, 100_000, 1_000_000], 2000, 1_000_000, 2000, 300, 20_000,
             300, [10, 100, 500], 1000, (3000, 1200, 10_000), (5000, 50_000))
QUICK = Scale(True, 500, 1, 50, 2000, [1000, 10_000, 100_000], 500, 100_000, 500, 50, 5000,
              60, [10, 100, 500], 100, (500, 120, 1000), (1000, 5000), 90)
SMOKE = Scale(True, 100, 1, 10, 500, [1000, 5000], 100, 10_000, 100, 10, 100,
              15, [10, 20], 20, (100, 20, 200), (200, 500), 15)


def _measure(sc: Scale, work: Path, log: Callable[[str], None]) -> tuple[Results, dict[int, float], dict[str, Any]]:
    """Every measurement, in an order that keeps each server's neighbours quiet."""
    n, rounds = sc.n, sc.rounds
    log("floors: raw TCP")
    tcp = floors.tcp(n)
    log("peer: redis")
    peer = redis_peer.run(n, work)
    log("peer: zenoh put -> subscriber")
    zenoh = _zenoh_latency(n)
    echo, m1, m1p, m2, m3, m4, scaling = _on_one_server(sc, work, log)
    log("M5 in process")
    m5 = cast_cases.m5_in_process(n)
    log("M6 large WM")
    m6_floor = floors.EchoFloor()
    try:
        m6 = cast_cases.m6_large(work / "big", sc.m6_checkpoints, sc.m6_probe, m6_floor)
    finally:
        m6_floor.close()
    log(f"R1 writers with a stalled watcher ({sc.r1_events:,} events per run)")
    r1 = stalled_watcher.run(work / "stalled", sc.r1_events, sc.r1_calls, rounds)
    d1 = durability.run(work / "d1", n, sc.d1_batches, n, log)
    log("M7 C++ and Java clients")
    m7 = other_clients.run(work / "m7", n, python_add_per_s=m1["add_per_s"], python_latency_p50=m3["p50_us"],
                           rounds=rounds, jit_warm=sc.jit_warm, log=log)
    m7_samples: dict[str, Any] = m7.pop("samples_us", {})
    m8 = images.run(work / "m8", sc.m8_frames, log)
    m9 = many_components.run(work / "m9", sc.m9_counts, sc.m9_writes, log)
    m10 = ros_bridge.run(work / "m10", sc.m10_frames, log)
    log("O1 what the metrics cost")
    o1 = metrics_overhead.run(work / "o1", *sc.o1, 1 if sc.quick else 3, log)
    log("REC1 what recording costs")
    rec1 = recording.run(work / "rec1", *sc.rec1, log)
    results = Results(tcp, peer, echo, m1, m2, m3, m4, m5, m6, m7, r1, d1, o1, rec1, zenoh=zenoh, m1p=m1p, m8=m8, m9=m9,
                      m10=m10)
    return results, scaling, m7_samples


def _zenoh_latency(n: int) -> dict[str, Any]:
    """Zenoh's put -> subscriber at M3's spacing, or why it could not be measured."""
    try:
        return zenoh_peer.latency(n, floors.GAP_S)
    except (RuntimeError, OSError, ImportError) as exc:
        return {"error": str(exc)}


def _on_one_server(sc: Scale, work: Path, log: Callable[[str], None]) -> tuple[Any, ...]:
    """The grpc echo floor, M1 (interleaved with it), M2, M3 and M4 against one `cast serve`."""
    n, rounds = sc.n, sc.rounds
    server = cast_cases.Server(work / "main", ["bench", "fanout"])
    echo_floor = floors.EchoFloor()
    try:
        log("floor: grpc echo latencies")
        lat_runs = [echo_floor.latencies(n) for _ in range(rounds)]
        echo = {
            "unary_p50_us": statistics.median(e["unary"]["p50_us"] for e in lat_runs),
            "stream_ping_pong_p50_us": statistics.median(e["stream_ping_pong"]["p50_us"] for e in lat_runs),
            "unary_spaced_p50_us": statistics.median(e["unary_spaced"]["p50_us"] for e in lat_runs),
        }
        log("M1 sequential, in blocks interleaved with the grpc echo and stream ping-pong floors")
        m1 = stream_cases.m1_both_floors(server, echo_floor, n * rounds)
        echo["unary_calls_per_s"] = m1.pop("echo_per_s")
        echo["stream_calls_per_s"] = m1.pop("stream_per_s")
        log("M1P pipelined adds (64 in flight), in blocks with sequential adds")
        m1p = stream_cases.pipelined_adds(server, n * rounds)
        log("M2 batch")
        m2 = cast_cases.m2_batch(server, sc.m2_batches)
        log("M3 write -> event latency")
        m3 = cast_cases.m3_latency(server, n)
        log("M4 fan-out")
        fan_events = sc.fan_events
        m4 = cast_cases.m4_fanout(server, fan_events)
        scaling: dict[int, float] = {}
        for w in () if sc.quick else (1, 2, 4, 8):
            log(f"M4 fan-out scaling: {w} watchers")
            scaling[w] = cast_cases.m4_fanout(server, fan_events, watchers=w, processes=min(w, 4))["delivered_per_s"]
        scaling[16] = m4["delivered_per_s"]
    finally:
        echo_floor.close()
        server.stop()
    return echo, m1, m1p, m2, m3, m4, scaling


def _write(out: Path, results: Results, command: str) -> None:
    """bench/results/latest.md and latest.json, with the floors and the peer measured in the run."""
    tcp, peer, echo = results.tcp, results.peer, results.echo
    machine = report.machine_info(
        {
            "raw TCP ping-pong p50": f"{tcp['p50_us']} µs ({tcp['round_trips_per_s']} round trips/s)",
            "grpcio unary echo": f"{results.unary_cps:.0f} calls/s, p50 {results.unary_p50} µs back to back, "
            f"{results.spaced_p50} µs with 2 ms spacing",
            "grpcio bidi-stream ping-pong": f"{echo['stream_calls_per_s']:.0f} calls/s in M1's blocks, p50 "
            f"{echo['stream_ping_pong_p50_us']} µs back to back",
            "redis-py SET / GET": f"{peer['set_ops_per_s']} / {peer['get_ops_per_s']} ops/s",
            "Redis SET -> keyspace notification": f"p50 {results.redis_p50} µs, "
            f"p99 {peer['notification']['p99_us']} µs",
            "Zenoh put -> subscriber (peer mode, loopback, 2 ms spacing)": f"p50 {results.zenoh.get('p50_us')} µs, "
            f"p99 {results.zenoh.get('p99_us')} µs (eclipse-zenoh {_zenoh_version()})",
            "iceoryx2 (M8's zero-copy limit)": iceoryx2_peer.iceoryx2_version(),
            "grpcio unary echo of 1 MiB (M8, for context)": ", ".join(
                f"{f['mb_per_s']} MB/s (p50 {f['p50_us']} µs)" for f in results.m8.get("floor", [])
            )
            or "not measured",
        },
        peer["version"],
    )
    table = rows(results)
    report.write_markdown(out / "latest.md", table, machine, command)
    report.write_json(out / "latest.json", table, machine)


def _zenoh_version() -> str:
    try:
        return zenoh_peer.zenoh_version()
    except ImportError:
        return "not installed"


def _plot(out: Path, results: Results, scaling: dict[int, float], m7_samples: dict[str, Any]) -> None:
    """The latency CDF, fan-out scaling, WM size and M9 plots."""
    report.plot_latency_cdf(
        out / "latency_cdf.png",
        {
            "CAST write -> event (Python -> Python)": results.m3["samples_us"],
            **{f"CAST write -> event ({lang})": s for lang, s in m7_samples.items()},
        },
    )
    ws = sorted(scaling)
    report.plot_xy(out / "fanout.png", ws, [scaling[w] for w in ws], "watchers", "delivered events/s",
                   "Fan-out: one writer, N watchers")
    sizes = sorted(int(k) for k in results.m6["rates"])
    report.plot_xy(out / "wm_size.png", sizes, [results.m6["rates"][str(s)] for s in sizes], "entries in the WM",
                   "sequential Add/s", "Add throughput against WM size")
    m9 = {int(k): v for k, v in results.m9.get("counts", {}).items() if "error" not in v}
    ns = sorted(m9)
    if ns:
        report.plot_panels(
            out / "many_components.png",
            ns,
            {
                "write -> event (µs)": {q: [m9[n][f"{q}_us"] for n in ns] for q in ("p50", "p99")},
                "server CPU while writing (cores)": {"CPU": [m9[n]["busy_cpu"] for n in ns]},
                "server RSS per session (KiB)": {"RSS": [m9[n]["rss_per_session_kib"] for n in ns]},
                "time to register all (s)": {"register": [m9[n]["register_s"] for n in ns]},
            },
            "component sessions",
            "M9: many components, one writer adding at 100/s",
            log_y=["write -> event (µs)"],
        )


if __name__ == "__main__":
    sys.exit(main())
