"""`python -m bench.run [--quick]`: floors, peer and CAST in one run; writes bench/results/."""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import cast_cases, durability, floors, other_clients, redis_peer, report, stalled_watcher
from bench.harness import ROOT

RESULTS = ROOT / "bench" / "results"


def _fig(name: str, value: float, floor: float | None = None, peer: float | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"name": name, "value": value}
    if floor is not None:
        out["floor"] = floor
    if peer is not None:
        out["peer"] = peer
    return out


def main(argv: list[str] | None = None) -> int:
    """Run every benchmark and write the report."""
    parser = argparse.ArgumentParser(prog="bench.run")
    parser.add_argument("--quick", action="store_true", help="smaller counts (under 2 minutes)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    q = args.quick
    n = 500 if q else 3000
    rounds = 1 if q else 3
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="cast-bench-"))
    t_start = time.time()

    def log(msg: str) -> None:
        print(f"[{time.time() - t_start:6.1f}s] {msg}", flush=True)

    log("floors: raw TCP")
    tcp = floors.tcp(n)
    log("peer: redis")
    peer = redis_peer.run(n, work)
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
        log("M1 sequential, in blocks interleaved with the grpc echo floor")
        m1_all = cast_cases.m1_interleaved(server, echo_floor, n * rounds)
        echo["unary_calls_per_s"] = m1_all.pop("echo_per_s")
        m1 = m1_all
        log("M2 batch")
        m2 = cast_cases.m2_batch(server, 50 if q else 300)
        log("M3 write -> event latency")
        m3 = cast_cases.m3_latency(server, n)
        log("M4 fan-out")
        fan_events = 2000 if q else 10000
        m4 = cast_cases.m4_fanout(server, fan_events)
        scaling = {}
        if not q:
            for w in (1, 2, 4, 8):
                log(f"M4 fan-out scaling: {w} watchers")
                scaling[w] = cast_cases.m4_fanout(server, fan_events, watchers=w, processes=min(w, 4))[
                    "delivered_per_s"
                ]
        scaling[16] = m4["delivered_per_s"]
    finally:
        echo_floor.close()
        server.stop()
    log("M5 in process")
    m5 = cast_cases.m5_in_process(n)
    log("M6 large WM")
    checkpoints = [1000, 10_000, 100_000] if q else [1000, 10_000, 100_000, 1_000_000]
    m6_floor = floors.EchoFloor()
    try:
        m6 = cast_cases.m6_large(work / "big", checkpoints, 500 if q else 2000, m6_floor)
    finally:
        m6_floor.close()
    stalled_events = 100_000 if q else 1_000_000
    log(f"R1 writers with a stalled watcher ({stalled_events:,} events per run)")
    r1 = stalled_watcher.run(work / "stalled", stalled_events, 500 if q else 2000, rounds)
    d1 = durability.run(work / "d1", n, 50 if q else 300, n, log)
    log("M7 C++ and Java clients")
    m7 = other_clients.run(
        work / "m7",
        n,
        python_add_per_s=m1["add_per_s"],
        python_latency_p50=m3["p50_us"],
        rounds=rounds,
        jit_warm=5000 if q else 20_000,
        log=log,
    )
    m7_samples: dict[str, list[float]] = m7.pop("samples_us", {})

    unary_cps = echo["unary_calls_per_s"]
    unary_p50 = echo["unary_p50_us"]
    spaced_p50 = echo["unary_spaced_p50_us"]
    redis_p50 = peer["notification"]["p50_us"]
    write_event_floor = unary_p50 / 2 + echo["stream_ping_pong_p50_us"] / 2
    rows: list[dict[str, Any]] = [
        {
            "id": "M1",
            "what": "sequential Add, Get, Overwrite from one Python client (calls/s)",
            "target": ">= 0.8 x bare grpcio unary echo calls/s",
            "figures": [_fig(f"{k} (calls/s)", v, floor=unary_cps) for k, v in m1.items()],
            "met": all(v >= 0.8 * unary_cps for v in m1.values()),
        },
        {
            "id": "M2",
            "what": "Batch of 100 adds (entries/s)",
            "target": ">= 3 x redis-py sequential SET ops/s",
            "figures": [_fig("entries/s", m2["entries_per_s"], peer=peer["set_ops_per_s"])],
            "met": m2["entries_per_s"] >= 3 * peer["set_ops_per_s"],
        },
        {
            "id": "M3",
            "what": "write -> event latency, Python writer -> Python watcher (µs)",
            "target": "p50 <= 1.5 x grpcio unary p50 (same 2 ms spacing) and <= 2 x Redis notification p50; "
            "p99 <= 3000 µs",
            "figures": [
                _fig("p50 (µs)", m3["p50_us"], floor=spaced_p50, peer=redis_p50),
                _fig("p99 (µs)", m3["p99_us"], peer=peer["notification"]["p99_us"]),
                _fig("lost", m3["lost"]),
            ],
            "note": (
                f"2 x Redis's notification p50 is {2 * redis_p50:.0f} µs, below the floor of a gRPC write -> "
                f"event on this stack: half a bare unary round trip to carry the write in "
                f"({unary_p50 / 2:.0f} µs) plus half a bare stream ping-pong to carry the event out "
                f"({echo['stream_ping_pong_p50_us'] / 2:.0f} µs), {write_event_floor:.0f} µs before any work; "
                "no Python gRPC write -> event path can meet that part; see docs/performance.md"
            )
            if 2 * redis_p50 < write_event_floor
            else "",
            "met": m3["p50_us"] <= 1.5 * spaced_p50
            and m3["p50_us"] <= 2 * redis_p50
            and m3["p99_us"] <= 3000
            and m3["lost"] == 0,
        },
        {
            "id": "M4",
            "what": "fan-out: one writer, 16 watchers each receiving every event",
            "target": ">= 50,000 delivered events/s in total, 0 lost, 0 out of order",
            "figures": [
                _fig("delivered events/s", m4["delivered_per_s"]),
                _fig("lost", m4["lost"]),
                _fig("out of order", m4["out_of_order"]),
                _fig("duplicates", m4["duplicates"]),
            ],
            "met": m4["delivered_per_s"] >= 50_000
            and m4["lost"] == 0
            and m4["out_of_order"] == 0
            and m4["duplicates"] == 0,
        },
        {
            "id": "M5",
            "what": "in-process component: add -> its own callback; get (µs)",
            "target": "add -> callback p50 <= 50 µs; get p50 <= 10 µs",
            "figures": [
                _fig("add -> callback p50 (µs)", m5["add_to_callback"]["p50_us"], floor=m5["handoff"]["p50_us"]),
                _fig("add -> callback p99 (µs)", m5["add_to_callback"]["p99_us"]),
                _fig("get p50 (µs)", m5["get"]["p50_us"]),
            ],
            "note": (
                f"the floor is the thread handoff alone: a callback that only stamps, submitted straight to the "
                f"component's dispatcher thread, measured back to back in blocks alternating with ours: p50 "
                f"{m5['handoff']['p50_us']} µs, so the write and its event add "
                f"{m5['add_to_callback']['p50_us'] - m5['handoff']['p50_us']:.1f} µs; the handoff costs ~5 µs when "
                "the machine runs both threads on one CPU and 30-40 µs when on two (a cross-CPU wake-up on this "
                "VM); see docs/performance.md, M5"
            ),
            "met": m5["add_to_callback"]["p50_us"] <= 50 and m5["get"]["p50_us"] <= 10,
        },
        {
            "id": "M6",
            "what": f"{m6['entries']:,} entries of 100 bytes in one WM",
            "target": "server RSS <= 1 GiB; get_all of a type with 10 entries <= 2 ms; "
            "Add at full size within 15% of at 1k",
            "figures": [
                _fig("server RSS (MiB)", m6["server_rss_mib"]),
                _fig("get_all of 10 p50 (ms)", m6["get_all_10_p50_ms"]),
                _fig("Add/s at 1k entries", m6["add_per_s_at_small"]),
                _fig(f"Add/s at {m6['entries']:,} entries", m6["add_per_s_at_full"], floor=m6["add_per_s_at_small"]),
                _fig(
                    "Add at full size / at 1k, each relative to the echo floor measured with it", m6["add_rate_ratio"]
                ),
            ],
            "met": m6["server_rss_mib"] <= 1024 and m6["get_all_10_p50_ms"] <= 2 and m6["add_rate_ratio"] >= 0.85,
        },
        m7,
        _durability_row(d1),
        {
            "id": "R1",
            "what": f"writers while a watcher has stopped reading, {r1['events']:,} events per run (issue 7), "
            "against the same writes with no watcher",
            "target": "writers slowed by at most 20% (>= 0.8 x the rate without the watcher)",
            "figures": [
                _fig(
                    "Batch of 1,000 overwrites, events/s",
                    r1["batch_events_per_s_with"],
                    floor=r1["batch_events_per_s_without"],
                ),
                _fig("sequential Overwrite calls/s", r1["sequential_per_s_with"], floor=r1["sequential_per_s_without"]),
            ],
            "met": r1["batch_ratio"] >= 0.8 and r1["sequential_ratio"] >= 0.8,
        },
    ]
    machine = report.machine_info(
        {
            "raw TCP ping-pong p50": f"{tcp['p50_us']} µs ({tcp['round_trips_per_s']} round trips/s)",
            "grpcio unary echo": f"{unary_cps:.0f} calls/s, p50 {unary_p50} µs back to back, "
            f"{spaced_p50} µs with 2 ms spacing",
            "grpcio bidi-stream ping-pong p50": f"{echo['stream_ping_pong_p50_us']} µs",
            "redis-py SET / GET": f"{peer['set_ops_per_s']} / {peer['get_ops_per_s']} ops/s",
            "Redis SET -> keyspace notification": f"p50 {redis_p50} µs, p99 {peer['notification']['p99_us']} µs",
        },
        peer["version"],
    )
    command = "make bench-quick" if q else "make bench"
    report.write_markdown(out / "latest.md", rows, machine, command)
    report.write_json(out / "latest.json", rows, machine)
    report.plot_latency_cdf(
        out / "latency_cdf.png",
        {
            "CAST write -> event (Python -> Python)": m3["samples_us"],
            **{f"CAST write -> event ({lang})": s for lang, s in m7_samples.items()},
        },
    )
    ws = sorted(scaling)
    report.plot_xy(
        out / "fanout.png",
        ws,
        [scaling[w] for w in ws],
        "watchers",
        "delivered events/s",
        "Fan-out: one writer, N watchers",
    )
    sizes = sorted(int(k) for k in m6["rates"])
    report.plot_xy(
        out / "wm_size.png",
        sizes,
        [m6["rates"][str(s)] for s in sizes],
        "entries in the WM",
        "sequential Add/s",
        "Add throughput against WM size",
    )
    log(f"wrote {out / 'latest.md'}")
    print((out / "latest.md").read_text())
    return 0


def _durability_row(d1: dict[str, dict[str, float]]) -> dict[str, Any]:
    """D1: each durable mode's figures against memory only, measured with them in turns."""
    memory = d1["memory"]
    figures = []
    for mode in ("none", "batch", "always"):
        fig = d1[mode]
        figures += [
            _fig(f"{mode}: Add (calls/s)", fig["add_per_s"], floor=memory["add_per_s"]),
            _fig(f"{mode}: Get (calls/s)", fig["get_per_s"], floor=memory["get_per_s"]),
            _fig(f"{mode}: Overwrite (calls/s)", fig["overwrite_per_s"], floor=memory["overwrite_per_s"]),
            _fig(f"{mode}: Batch of 100 adds (entries/s)", fig["batch_entries_per_s"],
                 floor=memory["batch_entries_per_s"]),
            _fig(f"{mode}: write -> event p50 (µs)", fig["p50_us"], floor=memory["p50_us"]),
        ]
    gets_ok = all(d1[mode]["get_per_s"] >= 0.9 * memory["get_per_s"] for mode in ("none", "batch", "always"))
    return {
        "id": "D1",
        "what": "durability modes (issue 12): M1, M2, M3 against a server per mode, taking turns; the floor "
        "column is memory only",
        "target": "no target for writes (the cost is shown); reads never wait for the journal: Get >= 0.9 x "
        "memory only in every mode; no event lost",
        "figures": figures,
        "note": "in always and batch a write is answered, and becomes visible to anyone, once its transaction "
        "is fsynced; always makes one transaction per write call, batch one per group of concurrent ones",
        "met": gets_ok and all(d1[mode]["lost"] == 0 for mode in d1),
    }


if __name__ == "__main__":
    sys.exit(main())
