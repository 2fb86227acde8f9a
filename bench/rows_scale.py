"""The rows of the server under size and numbers: M8 (1 MiB entries to four watchers), M9 (many components).

Pure functions of one run's results (see bench/rows.py for the table and the other rows).
"""

from __future__ import annotations

import math
import statistics
from typing import Any

from bench.rows import fig

__all__ = ["M8_P99_US", "m8_misses", "m8_row", "m8_rss_bound", "m9_misses", "m9_row"]

M8_P99_US = 20_000
M8_FLOOR_SHARE = 0.5
M8_RSS_SLACK = 64 << 20  # the server's own buffers beyond its history (see m8_rss_bound)
M9_GROWTH = 3.0


def m8_rss_bound(m8: dict[str, Any]) -> int:
    """The server's RSS bound in M8: idle RSS + limits.history_bytes + M8_RSS_SLACK (docs/performance.md, M8)."""
    return int(m8["server_rss_idle"] + m8["history_bytes"] + M8_RSS_SLACK)


def _floor_mb(m8: dict[str, Any]) -> float:
    return statistics.fmean(f["mb_per_s"] for f in m8["floor"]) if m8.get("floor") else math.nan


def _floor_p50(m8: dict[str, Any]) -> float | None:
    """The bare 1 MiB unary echo's round-trip p50 (µs), the floor of M8's latencies: one value in, one out."""
    return round(statistics.fmean(f["p50_us"] for f in m8["floor"]), 1) if m8.get("floor") else None


def m8_misses(m8: dict[str, Any]) -> list[str]:
    """What M8 missed (empty: met): p99 at 30 Hz, losses, back-to-back MB/s (queue), server RSS."""
    if "error" in m8:
        return [m8["error"]]
    misses = []
    for delivery in ("queue", "latest"):
        for phase in ("hz", "b2b"):
            got = m8.get(f"cast_{delivery}_{phase}", {"error": "not run"})
            if "error" in got:
                misses.append(f"{delivery} {phase}: {got['error']}")
                continue
            if got.get("missing"):
                misses += [f"{label}: {why}" for label, why in got["missing"].items()]
            for label, w in got["watchers"].items():
                if w["lost"]:
                    misses.append(f"{delivery} {phase}: {label} lost {w['lost']}")
                if phase == "hz" and not w["p99_us"] <= M8_P99_US:
                    misses.append(f"{delivery} {HZ_LABEL}: {label} p99 {w['p99_us']:.0f} µs > {M8_P99_US}")
    b2b = m8.get("cast_queue_b2b", {})
    if "total" in b2b and not b2b["total"]["mb_per_s"] >= M8_FLOOR_SHARE * _floor_mb(m8):
        misses.append(f"queue back to back: {b2b['total']['mb_per_s']} MB/s < {M8_FLOOR_SHARE} x the 1 MiB echo's "
                      f"{_floor_mb(m8):.0f}")
    peak = max((m8[k]["server_rss_peak"] for k in m8 if k.startswith("cast_") and "server_rss_peak" in m8[k]),
               default=0)
    if peak > m8_rss_bound(m8):
        misses.append(f"server RSS peak {peak / 2**20:.0f} MiB > bound {m8_rss_bound(m8) / 2**20:.0f} MiB")
    return misses


HZ_LABEL = "30 Hz"


def _median(watchers: dict[str, Any], key: str) -> float:
    return round(float(statistics.median(w[key] for w in watchers.values())), 1)


def m8_row(m8: dict[str, Any]) -> dict[str, Any]:
    """M8: 1 MiB entries from a C++ writer to four watchers (Python, C++, Java, Python); Zenoh and Redis alike."""
    row: dict[str, Any] = {
        "id": "M8",
        "what": "1 MiB entry overwritten by a C++ writer at 30 Hz and back to back, four watchers (Python, C++, "
        "Java, Python), queue and latest delivery; peers: Zenoh and Redis with four Python subscribers",
        "target": f"30 Hz: p99 <= {M8_P99_US} µs to every watcher, 0 lost; back to back (queue): delivered MB/s of "
        f"all watchers >= {M8_FLOOR_SHARE} x bare 1 MiB unary echo MB/s; server RSS <= idle + history_bytes + "
        f"{M8_RSS_SLACK >> 20} MiB",
        "figures": [],
        "met": False,
    }
    misses = m8_misses(m8)
    row["met"] = not misses
    if misses:
        row["note"] = "; ".join(misses)
    if "error" in m8:
        return row
    zen_hz, zen_b2b = m8.get("zenoh_hz", {}), m8.get("zenoh_b2b", {})
    figures = row["figures"]
    for delivery in ("queue", "latest"):
        hz, b2b = m8.get(f"cast_{delivery}_hz", {}), m8.get(f"cast_{delivery}_b2b", {})
        for label, w in hz.get("watchers", {}).items():
            zp50 = _median(zen_hz["watchers"], "p50_us") if "watchers" in zen_hz else None
            zp99 = _median(zen_hz["watchers"], "p99_us") if "watchers" in zen_hz else None
            figures.append(fig(f"{delivery}, 30 Hz, {label}: p50 (µs)", w["p50_us"], floor=_floor_p50(m8), peer=zp50))
            figures.append(fig(f"{delivery}, 30 Hz, {label}: p99 (µs)", w["p99_us"], peer=zp99))
        if "watchers" in hz:
            lost = sum(w["lost"] for w in hz["watchers"].values())
            figures.append(fig(f"{delivery}, 30 Hz: lost, all watchers", lost))
        if "total" in b2b:
            zen_mb = zen_b2b["total"]["mb_per_s"] if "total" in zen_b2b else None
            figures.append(fig(f"{delivery}, back to back: MB/s delivered, all watchers", b2b["total"]["mb_per_s"],
                               floor=round(_floor_mb(m8), 1), peer=zen_mb))
            slowest = min(b2b["watchers"].items(), key=lambda kv: kv[1]["mb_per_s"])
            figures.append(fig(f"{delivery}, back to back: MB/s to the slowest watcher ({slowest[0]})",
                               slowest[1]["mb_per_s"]))
            figures.append(fig(f"{delivery}, back to back: lost, all watchers",
                               sum(w["lost"] for w in b2b["watchers"].values())))
            if delivery == "latest":
                figures.append(fig("latest, back to back: skipped (reported), all watchers",
                                   sum(w["skipped"] for w in b2b["watchers"].values())))
    peaks = [m8[k]["server_rss_peak"] for k in m8 if k.startswith("cast_") and "server_rss_peak" in m8[k]]
    if peaks:
        figures.append(fig(f"server RSS peak (MiB); idle {m8['server_rss_idle'] / 2**20:.0f}, bound "
                           f"{m8_rss_bound(m8) / 2**20:.0f}", round(max(peaks) / 2**20, 1)))
    for name in ("redis", "zenoh"):
        for phase in ("hz", "b2b"):
            got = m8.get(f"{name}_{phase}", {})
            if "watchers" not in got:
                continue
            title = name.capitalize()
            if phase == "hz":
                for q in ("p50", "p99"):
                    figures.append(fig(f"{title}, 30 Hz: {q} (µs), median of subscribers",
                                       _median(got["watchers"], f"{q}_us")))
            else:
                figures.append(fig(f"{title}, back to back: MB/s delivered, all subscribers",
                                   got["total"]["mb_per_s"], floor=round(_floor_mb(m8), 1)))
    return row


def m9_misses(m9: dict[str, Any]) -> list[str]:
    """What M9 missed: p99 at the largest count against the smallest, losses, failures."""
    counts = m9["counts"]
    misses = [f"{k} sessions: {v['error']}" for k, v in counts.items() if "error" in v]
    ok = {int(k): v for k, v in counts.items() if "error" not in v}
    misses += [f"{k} sessions: {v['lost']} events lost" for k, v in sorted(ok.items()) if v["lost"]]
    if len(ok) >= 2:
        low, high = ok[min(ok)], ok[max(ok)]
        if not high["p99_us"] <= M9_GROWTH * low["p99_us"]:
            misses.append(f"p99 at {max(ok)} sessions {high['p99_us']:.0f} µs > {M9_GROWTH} x its value at "
                          f"{min(ok)} ({low['p99_us']:.0f} µs)")
    elif not misses:
        misses.append("fewer than two counts measured")
    return misses


def m9_row(m9: dict[str, Any]) -> dict[str, Any]:
    """M9: many component sessions, each beating and watching, one writer adding at 100/s."""
    figures = []
    counts = {int(k): v for k, v in m9["counts"].items() if "error" not in v}
    low = counts[min(counts)] if counts else None
    for n, v in sorted(counts.items()):
        figures += [
            fig(f"{n} sessions: write -> event p50 (µs)", v["p50_us"], floor=low["p50_us"] if low else None),
            fig(f"{n} sessions: p99 (µs)", v["p99_us"], floor=low["p99_us"] if low else None),
            fig(f"{n} sessions: lost", v["lost"]),
            fig(f"{n} sessions: time to register all (s)", v["register_s"]),
            fig(f"{n} sessions: server RSS per session (KiB)", v["rss_per_session_kib"]),
            fig(f"{n} sessions: server CPU while writing (cores)", v["busy_cpu"]),
            fig(f"{n} sessions: load generators' CPU while writing (cores)", v.get("load_cpu", float("nan"))),
        ]
    misses = m9_misses(m9)
    row: dict[str, Any] = {
        "id": "M9",
        "what": f"many components: N sessions (heartbeats and one watch each, in {m9['processes']} load processes) "
        f"while one writer adds at 100/s; the floor column is the smallest N",
        "target": f"at the largest N, p99 <= {M9_GROWTH} x its value at the smallest; 0 lost; RSS per session "
        "documented",
        "figures": figures,
        "met": not misses,
    }
    if misses:
        row["note"] = "; ".join(misses)
    return row
