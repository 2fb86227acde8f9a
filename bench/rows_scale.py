"""The rows of the server under size and numbers: M8 (large values to four watchers), M9 (many components).

Pure functions of one run's results (see bench/rows.py for the table and the other rows).
"""

from __future__ import annotations

import math
import statistics
from typing import Any

from bench.delivery_stats import ordinal
from bench.rows import fig

__all__ = ["M8_BIG_P99_US", "M8_P99_US", "M8_PHASES", "m8_memory_bound", "m8_misses", "m8_row", "m9_misses", "m9_row"]

M8_P99_US = 5_000  # 1 MiB at 30 Hz, to every watcher
M8_BIG_P99_US = 10_000  # 6 MiB at 30 Hz, to every watcher
M8_ZENOH_P50 = 1.0  # each watcher's p50 against Zenoh's (median of its subscribers), 1 MiB at 30 Hz
M8_ZENOH_MB = 1.0  # MB/s to the four together, back to back, against Zenoh's
M8_SEGMENT = 64 << 20  # the arena grows by whole segments of this size (cast.core.shared.SEGMENT_BYTES)
M8_STAGING = 16 << 20  # a session's staging area: 2 x limits.max_value_bytes (8 MiB by default)
M8_SESSIONS = 5  # the writer and the four watchers each have a shared-memory session with the server
M8_SLACK = 64 << 20  # the server's own buffers beyond its history and its arena (see m8_memory_bound)
M8_PHASES = {  # bench/images.py's phases on the server's host: key -> how the row names it
    "queue_hz": "1 MiB, queue, 30 Hz",
    "queue_hz_6m": "6 MiB, queue, 30 Hz",
    "queue_b2b": "1 MiB, queue, back to back",
    "latest_b2b": "1 MiB, latest, back to back",
}
RELAY = "bare Python relay (CAST's two hops and one copy, no rules), 1 MiB, 30 Hz"  # bench/relay_floor.py
M9_GROWTH = 3.0


def m8_memory_bound(m8: dict[str, Any]) -> int:
    """The server's memory bound in M8 (docs/performance.md, M8).

    Idle (private resident memory plus shared memory) + limits.history_bytes
    (which counts the values kept in shared memory too) + two arena segments
    (the arena grows by whole segments; a large value needs a free extent of its
    size; values lent to a watcher stay after they leave the history) + a
    staging area per session (the server makes one for each client, watchers
    too, counted at its full size) + M8_SLACK (gRPC's buffers and the allocator's).
    """
    return int(m8["server_memory_idle"] + m8["history_bytes"] + 2 * M8_SEGMENT + M8_SESSIONS * M8_STAGING
               + M8_SLACK)


def _median(watchers: dict[str, Any], key: str) -> float:
    return round(float(statistics.median(w[key] for w in watchers.values())), 1)


def _peer_median(m8: dict[str, Any], key: str, figure: str) -> float | None:
    watchers = m8.get(key, {}).get("watchers")
    return _median(watchers, figure) if watchers and all(figure in w for w in watchers.values()) else None


def _peer_total(m8: dict[str, Any], key: str) -> float | None:
    got = m8.get(key, {})
    return float(got["total"]["mb_per_s"]) if "total" in got else None


def _read_misses(what: str, label: str, w: dict[str, Any]) -> list[str]:
    misses = []
    if w["lost"]:
        misses.append(f"{what}: {label} lost {w['lost']}"
                      + (f" (its watch ended: {w['watch_ended']})" if w.get("watch_ended") else ""))
    if not w.get("checksum_ok"):
        misses.append(f"{what}: {label}'s checksum is not that of the bytes written (it did not read them all)")
    return misses


def _phase_misses(m8: dict[str, Any], key: str) -> list[str]:
    what = M8_PHASES[key]
    got = m8.get(f"cast_{key}", {"error": "not run"})
    if "error" in got:
        return [f"{what}: {got['error']}"]
    misses = [f"{label}: {why}" for label, why in got.get("missing", {}).items()]
    zen_p50 = _peer_median(m8, "zenoh_hz", "p50_us")
    for label, w in got["watchers"].items():
        misses += _read_misses(what, label, w)
        if key == "queue_hz":
            if not w["p99_us"] <= M8_P99_US:
                misses.append(f"{what}: {label} p99 {w['p99_us']:.0f} µs > {M8_P99_US}")
            if zen_p50 is not None and not w["p50_us"] <= M8_ZENOH_P50 * zen_p50:
                misses.append(f"{what}: {label} p50 {w['p50_us']:.0f} µs > {M8_ZENOH_P50} x Zenoh's {zen_p50:.0f}")
        if key == "queue_hz_6m" and not w["p99_us"] <= M8_BIG_P99_US:
            misses.append(f"{what}: {label} p99 {w['p99_us']:.0f} µs > {M8_BIG_P99_US}")
    zen_mb = _peer_total(m8, "zenoh_b2b")
    if key == "queue_b2b" and zen_mb is not None and not got["total"]["mb_per_s"] >= M8_ZENOH_MB * zen_mb:
        misses.append(f"{what}: {got['total']['mb_per_s']} MB/s to the four < {M8_ZENOH_MB} x Zenoh's {zen_mb}")
    return misses


def _remote_misses(m8: dict[str, Any]) -> list[str]:
    what = "1 MiB, queue, 30 Hz, other host"
    got = m8.get("cast_remote", {"error": "not run"})
    if "error" in got:
        return [f"{what}: {got['error']}"]
    misses = []
    for label, w in got["watchers"].items():
        misses += _read_misses(what, label, w)
        if w["bytes"] != got["frames"] * got["size"]:
            misses.append(f"{what}: {label} received {w['bytes']} bytes, not {got['frames']} x {got['size']}")
        if w.get("shared"):
            misses.append(f"{what}: {label} got {w['shared']} values by shared memory from another host")
    return misses


def _memory_peak(m8: dict[str, Any]) -> int:
    return max((m8[f"cast_{k}"]["server_memory"]["peak"] for k in M8_PHASES
                if "server_memory" in m8.get(f"cast_{k}", {})), default=0)


def m8_misses(m8: dict[str, Any]) -> list[str]:
    """What M8 missed (empty: met): the targets of each phase, every byte read, nothing lost, the memory bound."""
    if "error" in m8:
        return [m8["error"]]
    misses = []
    for key in M8_PHASES:
        misses += _phase_misses(m8, key)
    misses += _remote_misses(m8)
    for key, what in (("zenoh_hz", "Zenoh, 1 MiB, 30 Hz"), ("zenoh_hz_6m", "Zenoh, 6 MiB, 30 Hz"),
                      ("zenoh_b2b", "Zenoh, 1 MiB, back to back"), ("iceoryx2_hz", "iceoryx2, 1 MiB, 30 Hz"),
                      ("iceoryx2_b2b", "iceoryx2, 1 MiB, back to back"), ("relay_hz", RELAY)):
        got = m8.get(key, {"error": "not run"})
        if "error" in got:  # a comparison the row promises and could not make
            misses.append(f"{what}: {got['error']}")
    if _memory_peak(m8) > m8_memory_bound(m8):
        misses.append(f"server memory peak {_memory_peak(m8) / 2**20:.0f} MiB > bound "
                      f"{m8_memory_bound(m8) / 2**20:.0f} MiB")
    return misses


def _half_figures(m8: dict[str, Any], key: str, zen: str) -> list[dict[str, Any]]:
    """Each half of a phase measured in turns with Zenoh's (bench/images.py, bench/turns.py): its slowest watcher."""
    mine, theirs = m8.get(f"cast_{key}", {}).get("halves", []), m8.get(zen, {}).get("halves", [])
    figures = []
    for number, (ours, peer) in enumerate(zip(mine, theirs, strict=False), 1):
        if ours and peer:
            slowest = max(ours, key=lambda label: ours[label])
            figures.append(fig(f"{M8_PHASES[key]}, the {ordinal(number)} half of the turns: the slowest watcher's "
                               f"p50 ({slowest}, µs; peer: Zenoh's in the same half)", ours[slowest],
                               peer=round(float(statistics.median(peer.values())), 1)))
    return figures


def _cold_figures(m8: dict[str, Any], key: str, zen: str) -> list[dict[str, Any]]:
    """The phase's first seconds, before the warm-up (every reader cold): shown, not judged."""
    got = m8.get(f"cast_{key}", {})
    iox_key = "iceoryx2_hz" if key == "queue_hz" else ""
    figures = []
    for label, w in got.get("watchers", {}).items():
        if "cold_p50_us" not in w:
            continue
        for q in ("p50", "p99"):
            peers = {"floor": _peer_median(m8, iox_key, f"cold_{q}_us") if iox_key else None,
                     "peer": _peer_median(m8, zen, f"cold_{q}_us")}
            figures.append(fig(f"{M8_PHASES[key]}, first {m8.get('cold_s', 0):g} s (cold, not judged), {label}: "
                               f"{q} (µs)", w[f"cold_{q}_us"], **peers))
    return figures


def _cast_figures(m8: dict[str, Any]) -> list[dict[str, Any]]:
    figures = []
    iox = {q: _peer_median(m8, "iceoryx2_hz", f"{q}_us") for q in ("p50", "p99")}
    for key, zen in (("queue_hz", "zenoh_hz"), ("queue_hz_6m", "zenoh_hz_6m")):
        got = m8.get(f"cast_{key}", {})
        for label, w in got.get("watchers", {}).items():
            for q in ("p50", "p99"):
                floor = iox[q] if key == "queue_hz" else None
                figures.append(fig(f"{M8_PHASES[key]}, {label}: {q} (µs)", w[f"{q}_us"], floor=floor,
                                   peer=_peer_median(m8, zen, f"{q}_us")))
        if "watchers" in got:
            lost = sum(w["lost"] for w in got["watchers"].values())
            figures.append(fig(f"{M8_PHASES[key]}: lost, all watchers", lost))
        figures += _half_figures(m8, key, zen) + _cold_figures(m8, key, zen)
    for key in ("queue_b2b", "latest_b2b"):
        got = m8.get(f"cast_{key}", {})
        if "total" not in got:
            continue
        peers = {"floor": _peer_total(m8, "iceoryx2_b2b"), "peer": _peer_total(m8, "zenoh_b2b")}
        figures.append(fig(f"{M8_PHASES[key]}: MB/s delivered, all watchers", got["total"]["mb_per_s"],
                           **(peers if key == "queue_b2b" else {})))
        slowest = min(got["watchers"].items(), key=lambda kv: kv[1]["mb_per_s"])
        figures.append(fig(f"{M8_PHASES[key]}: MB/s to the slowest watcher ({slowest[0]})", slowest[1]["mb_per_s"]))
        figures.append(fig(f"{M8_PHASES[key]}: lost, all watchers", sum(w["lost"] for w in got["watchers"].values())))
        if key == "latest_b2b":
            figures.append(fig(f"{M8_PHASES[key]}: skipped (reported), all watchers",
                               sum(w["skipped"] for w in got["watchers"].values())))
    received = [w for k in M8_PHASES for w in m8.get(f"cast_{k}", {}).get("watchers", {}).values()]
    frames = sum(w["received"] for w in received)
    if frames:
        figures.append(fig("same host: values lent by shared memory, % of the values received",
                           round(100 * sum(w.get("shared", 0) for w in received) / frames, 1)))
    return figures


def _other_figures(m8: dict[str, Any]) -> list[dict[str, Any]]:
    figures = []
    remote = m8.get("cast_remote", {})
    for label, w in remote.get("watchers", {}).items():
        figures += [fig(f"1 MiB, 30 Hz, {label}: p50 (µs)", w["p50_us"]),
                    fig(f"1 MiB, 30 Hz, {label}: MB received as bytes (of {remote['frames']} frames)",
                        round(w["bytes"] / 1e6, 1)),
                    fig(f"1 MiB, 30 Hz, {label}: lost", w["lost"])]
    peak = _memory_peak(m8)
    if peak:
        parts = [m8[f"cast_{k}"]["server_memory"] for k in M8_PHASES if "server_memory" in m8.get(f"cast_{k}", {})]
        private, shared = (max(p[part] for p in parts) / 2**20 for part in ("private", "shared"))
        figures.append(fig(f"server memory peak (MiB: private resident + shared; their peaks {private:.0f} + "
                           f"{shared:.0f}); idle {m8['server_memory_idle'] / 2**20:.0f}, bound "
                           f"{m8_memory_bound(m8) / 2**20:.0f}", round(peak / 2**20, 1)))
    for key, what in (("zenoh_hz", "Zenoh, 1 MiB, 30 Hz"), ("zenoh_hz_6m", "Zenoh, 6 MiB, 30 Hz"),
                      ("iceoryx2_hz", "iceoryx2, 1 MiB, 30 Hz"), ("relay_hz", RELAY)):
        got = m8.get(key, {})
        if "error" in got:
            figures.append(fig(f"{what}: not measured ({got['error'][:120]})", math.nan))
            continue
        for q in ("p50", "p99"):
            if "watchers" in got:
                figures.append(fig(f"{what}: {q} (µs), median of subscribers", _median(got["watchers"], f"{q}_us")))
    for key, what in (("zenoh_b2b", "Zenoh, 1 MiB, back to back"), ("iceoryx2_b2b", "iceoryx2, 1 MiB, back to back")):
        got = m8.get(key, {})
        if "error" in got:
            figures.append(fig(f"{what}: not measured ({got['error'][:120]})", math.nan))
        elif "total" in got:
            figures.append(fig(f"{what}: MB/s delivered, all subscribers", got["total"]["mb_per_s"]))
    return figures


def m8_row(m8: dict[str, Any]) -> dict[str, Any]:
    """M8: 1 MiB and 6 MiB entries from a C++ writer to four watchers reading every byte; Zenoh, iceoryx2 alike."""
    row: dict[str, Any] = {
        "id": "M8",
        "what": "1 MiB and 6 MiB entries overwritten by a C++ writer, four watchers (Python, C++, Java, Python) "
        "reading every byte of every value (a checksum), queue delivery at 30 Hz and back to back, latest back to "
        "back, each phase measured after a warm-up burst of its frames to every reader (the first seconds of 1 MiB at "
        "30 Hz, cold, shown beside); the judged 1 MiB 30 Hz phase and Zenoh's at once, in turns (CAST's writer in "
        "the even seconds, Zenoh's publisher in the odd ones), each half shown beside; a Python watcher in "
        "another network namespace (bytes); peer Zenoh and floor iceoryx2 (zero-copy), a Python publisher and "
        "four Python subscribers reading every byte, same run; at 1 MiB 30 Hz also a bare Python relay between a "
        "writer and four readers (what the path costs)",
        "target": f"1 MiB at 30 Hz: every watcher's p50 <= {M8_ZENOH_P50} x Zenoh's, p99 <= {M8_P99_US} µs; 6 MiB "
        f"at 30 Hz: p99 <= {M8_BIG_P99_US} µs; 1 MiB back to back: MB/s to the four >= {M8_ZENOH_MB} x Zenoh's; "
        "0 lost, every checksum right, the other host gets every frame as bytes; server memory (private + "
        f"shared) <= idle + history_bytes + 2 x {M8_SEGMENT >> 20} MiB (arena segments) + {M8_SESSIONS} x "
        f"{M8_STAGING >> 20} MiB (a staging area per session) + {M8_SLACK >> 20} MiB",
        "figures": [],
        "met": False,
    }
    misses = m8_misses(m8)
    row["met"] = not misses
    if misses:
        row["note"] = "; ".join(misses)
    if "error" in m8:
        return row
    row["figures"] = _cast_figures(m8) + _other_figures(m8)
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
