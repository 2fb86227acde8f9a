"""The JSON shape of the metrics (``cast stats --json``, ``cast run --summary-json``'s ``metrics``).

Plain data only: histograms with their quantile estimates, and the merge of
several servers' snapshots into one system's. Each field and its unit is
documented in docs/experiments.md, "Metrics"; :mod:`cast.core.metrics` fills
it, the server translates it to and from ``cast.v1.GetMetricsResponse``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

__all__ = ["COUNTERS", "QUANTILES", "empty_snapshot", "histogram_json", "merge_snapshots", "quantile"]

COUNTERS = ("reads", "entries_read", "writes", "adds", "overwrites", "deletes", "writes_refused", "bytes_in",
            "bytes_out", "events", "event_bytes", "locks", "lock_waits", "lock_wait_s", "tasks_proposed",
            "tasks_adopted", "tasks_rejected", "tasks_retracted", "tasks_completed", "task_wait_s")
"""The counters of a component and of a WM (a WM has no ``writes_refused``), in this order."""

QUANTILES = (50, 90, 95, 99)
"""The quantiles a histogram's JSON estimates (``p50_s``, ...)."""

_TRAFFIC = ("reads", "writes", "bytes_in", "bytes_out", "events")


def quantile(counts: Sequence[int], bounds: Sequence[float], q: float) -> float:
    """The ``q``-quantile (0..1) estimated from bucket counts, as Prometheus's histogram_quantile does.

    Linear within the bucket it falls in (the first bucket starts at 0); in
    the bucket above the last bound, that bound. 0.0 for an empty histogram.
    """
    total = sum(counts)
    if total == 0:
        return 0.0
    rank = q * total
    seen = 0
    for i, n in enumerate(counts):
        if n and seen + n >= rank:
            if i >= len(bounds):
                return float(bounds[-1])
            low = bounds[i - 1] if i else 0.0
            return float(low + (bounds[i] - low) * (rank - seen) / n)
        seen += n
    return float(bounds[-1])


def histogram_json(counts: Sequence[int], sum_s: float, bounds: Sequence[float]) -> dict[str, Any]:
    """A histogram as JSON: count, sum and mean (seconds), estimated quantiles, the bucket counts."""
    count = sum(counts)
    out: dict[str, Any] = {"count": count, "sum_s": sum_s, "mean_s": sum_s / count if count else 0.0}
    for q in QUANTILES:
        out[f"p{q}_s"] = quantile(counts, bounds, q / 100)
    out["buckets"] = list(counts)
    return out


def empty_snapshot(system: str = "", bounds: Sequence[float] = ()) -> dict[str, Any]:
    """A snapshot of no server (what merging nothing gives)."""
    return {"enabled": True, "system": system, "servers": 0, "uptime_s": 0.0, "buckets_s": list(bounds),
            "components": {}, "subarchitectures": {}, "traffic": [],
            "delivery_latency": {"all": histogram_json([0] * (len(bounds) + 1), 0.0, bounds), "watchers": {}},
            "reports": {}, "shared_memory": None}


def _add_counters(into: dict[str, Any], more: dict[str, Any]) -> None:
    for name in COUNTERS:
        if name in more:
            into[name] = into.get(name, 0) + more[name]


def _merge_histogram(a: dict[str, Any], b: dict[str, Any], bounds: Sequence[float]) -> dict[str, Any]:
    counts = [x + y for x, y in zip(a["buckets"], b["buckets"], strict=True)]
    return histogram_json(counts, a["sum_s"] + b["sum_s"], bounds)


def merge_snapshots(snapshots: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One system's metrics from its servers' snapshots (each SA is on one server; a component uses several).

    Counters add up, histograms add bucket by bucket (quantiles estimated
    again), a report's count, sum, min and max combine and its last value is
    the latest. ``enabled`` only if every server counts; ``uptime_s`` the
    longest.
    """
    if not snapshots:
        return empty_snapshot()
    bounds = snapshots[0]["buckets_s"]
    out = empty_snapshot(snapshots[0]["system"], bounds)
    out["servers"] = 0
    traffic: dict[tuple[str, str], dict[str, Any]] = {}
    for snap in snapshots:
        if snap["buckets_s"] != bounds:
            raise ValueError("the servers' histograms have different buckets: they run different CAST versions")
        out["enabled"] = out["enabled"] and snap["enabled"]
        out["servers"] += snap["servers"]
        out["uptime_s"] = max(out["uptime_s"], snap["uptime_s"])
        for cid, counters in snap["components"].items():
            mine = out["components"].setdefault(cid, {"subarchitecture": counters["subarchitecture"]})
            _add_counters(mine, counters)
        for sa, counters in snap["subarchitectures"].items():
            known = out["subarchitectures"].get(sa)
            if known is None:
                out["subarchitectures"][sa] = {**counters}
            else:
                _add_counters(known, counters)
                known["task_wait"] = _merge_histogram(known["task_wait"], counters["task_wait"], bounds)
        for cell in snap["traffic"]:
            key = (cell["from_sa"], cell["to_sa"])
            into = traffic.setdefault(key, {"from_sa": key[0], "to_sa": key[1], **dict.fromkeys(_TRAFFIC, 0)})
            for name in _TRAFFIC:
                into[name] += cell[name]
        latency = out["delivery_latency"]
        latency["all"] = _merge_histogram(latency["all"], snap["delivery_latency"]["all"], bounds)
        for watcher, hist in snap["delivery_latency"]["watchers"].items():
            known = latency["watchers"].get(watcher)
            latency["watchers"][watcher] = {**hist} if known is None else {
                "subarchitecture": known["subarchitecture"], **_merge_histogram(known, hist, bounds)}
        for cid, named in snap["reports"].items():
            mine = out["reports"].setdefault(cid, {})
            for name, r in named.items():
                known = mine.get(name)
                if known is None:
                    mine[name] = {**r}
                    continue
                latest = r if r["last_time"] >= known["last_time"] else known
                count, total = known["count"] + r["count"], known["sum"] + r["sum"]
                mine[name] = {"count": count, "sum": total, "min": min(known["min"], r["min"]),
                              "max": max(known["max"], r["max"]), "last": latest["last"], "mean": total / count,
                              "last_time": latest["last_time"]}
        shared = snap.get("shared_memory")
        if shared:
            mine = out["shared_memory"] = out["shared_memory"] or {}
            for name, value in shared.items():
                # Every figure adds up over servers, but the threshold, which is each server's setting.
                mine[name] = max(mine.get(name, 0), value) if name == "threshold_bytes" else mine.get(name, 0) + value
    out["components"] = dict(sorted(out["components"].items()))
    out["traffic"] = [traffic[key] for key in sorted(traffic)]
    out["delivery_latency"]["watchers"] = dict(sorted(out["delivery_latency"]["watchers"].items()))
    return out
