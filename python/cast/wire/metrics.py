"""The metrics' JSON shape (cast.core.metrics_view) to ``cast.v1.GetMetricsResponse`` and back.

The server sends its snapshot with :func:`snapshot_to_pb`; ``cast stats`` and
``cast run`` read each server's answer back with :func:`snapshot_from_pb` and
merge them (:func:`cast.core.metrics_view.merge_snapshots`). Protobuf only.
"""

from __future__ import annotations

from typing import Any

from cast.core.metrics_view import COUNTERS, histogram_json
from cast.v1 import inspection_pb2 as insp_pb2
from cast.wire.values import timestamp

__all__ = ["snapshot_from_pb", "snapshot_to_pb"]

# JSON name -> MetricCounters field, where they differ (the wire spells units out).
_WIRE_NAMES = {"lock_wait_s": "lock_wait_seconds", "task_wait_s": "task_wait_seconds"}
_DERIVED = ("writes",)  # adds + overwrites + deletes: not on the wire
_TRAFFIC = ("reads", "writes", "bytes_in", "bytes_out", "events")


def _counters_to_pb(pb: insp_pb2.MetricCounters, counters: dict[str, Any]) -> None:
    for name in COUNTERS:
        if name in counters and name not in _DERIVED:
            setattr(pb, _WIRE_NAMES.get(name, name), counters[name])


def _counters_from_pb(pb: insp_pb2.MetricCounters, with_refused: bool) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in COUNTERS:
        if name == "writes":
            out[name] = pb.adds + pb.overwrites + pb.deletes
        elif name != "writes_refused" or with_refused:
            out[name] = getattr(pb, _WIRE_NAMES.get(name, name))
    return out


def snapshot_to_pb(snap: dict[str, Any]) -> insp_pb2.GetMetricsResponse:
    """One server's snapshot (:meth:`cast.core.metrics.Metrics.snapshot`) as the wire message."""
    pb = insp_pb2.GetMetricsResponse(system=snap["system"], enabled=snap["enabled"], uptime_seconds=snap["uptime_s"],
                                     bucket_bounds_seconds=snap["buckets_s"])
    for cid, counters in snap["components"].items():
        comp = pb.components.add(component=cid, subarchitecture=counters["subarchitecture"])
        _counters_to_pb(comp.counters, counters)
    for sa, counters in snap["subarchitectures"].items():
        wm = pb.subarchitectures.add(subarchitecture=sa)
        _counters_to_pb(wm.counters, counters)
        wm.task_wait.buckets.extend(counters["task_wait"]["buckets"])
        wm.task_wait.sum_seconds = counters["task_wait"]["sum_s"]
    for cell in snap["traffic"]:
        pb.traffic.add(from_sa=cell["from_sa"], to_sa=cell["to_sa"], **{k: cell[k] for k in _TRAFFIC})
    for watcher, hist in snap["delivery_latency"]["watchers"].items():
        lat = pb.latency.add(watcher=watcher, subarchitecture=hist["subarchitecture"])
        lat.latency.buckets.extend(hist["buckets"])
        lat.latency.sum_seconds = hist["sum_s"]
    for cid, named in snap["reports"].items():
        for name, r in named.items():
            pb.reports.add(component=cid, name=name, count=r["count"], sum=r["sum"], min=r["min"], max=r["max"],
                           last=r["last"], last_time=timestamp(round(r["last_time"] * 1e9)))
    shared = snap.get("shared_memory")
    if shared is not None:
        pb.shared_memory.CopyFrom(insp_pb2.SharedMemoryMetrics(**shared))
    return pb


def snapshot_from_pb(pb: insp_pb2.GetMetricsResponse) -> dict[str, Any]:
    """A server's answer in the JSON shape of ``cast stats --json`` (quantiles estimated from its buckets)."""
    bounds = list(pb.bucket_bounds_seconds)
    components = {c.component: {"subarchitecture": c.subarchitecture, **_counters_from_pb(c.counters, True)}
                  for c in pb.components}
    sas = {w.subarchitecture: {**_counters_from_pb(w.counters, False),
                               "task_wait": histogram_json(list(w.task_wait.buckets), w.task_wait.sum_seconds, bounds)}
           for w in pb.subarchitectures}
    traffic = [{"from_sa": t.from_sa, "to_sa": t.to_sa, **{k: getattr(t, k) for k in _TRAFFIC}} for t in pb.traffic]
    watchers: dict[str, Any] = {}
    everyone = [0] * (len(bounds) + 1)
    total = 0.0
    for lat in pb.latency:
        counts = list(lat.latency.buckets)
        everyone = [a + b for a, b in zip(everyone, counts, strict=True)]
        total += lat.latency.sum_seconds
        watchers[lat.watcher] = {"subarchitecture": lat.subarchitecture,
                                 **histogram_json(counts, lat.latency.sum_seconds, bounds)}
    reports: dict[str, dict[str, Any]] = {}
    for r in pb.reports:
        reports.setdefault(r.component, {})[r.name] = {
            "count": r.count, "sum": r.sum, "min": r.min, "max": r.max, "last": r.last,
            "mean": r.sum / r.count if r.count else 0.0,
            "last_time": r.last_time.seconds + r.last_time.nanos / 1e9}
    shared = ({field.name: getattr(pb.shared_memory, field.name) for field in pb.shared_memory.DESCRIPTOR.fields}
              if pb.HasField("shared_memory") else None)
    return {"enabled": pb.enabled, "system": pb.system, "servers": 1, "uptime_s": pb.uptime_seconds,
            "buckets_s": bounds, "components": components, "subarchitectures": sas, "traffic": traffic,
            "delivery_latency": {"all": histogram_json(everyone, total, bounds), "watchers": watchers},
            "reports": reports, "shared_memory": shared}
