"""The metrics in Prometheus's text format: ``--metrics HOST:PORT`` on ``cast serve`` and ``cast run``.

A custom collector turns a snapshot (the JSON shape of cast.core.metrics_view)
into metric families when /metrics is scraped, so that no call on the hot path
touches prometheus_client (docs/decisions.md). Names start with ``cast_``;
docs/experiments.md lists every family and its labels.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from threading import Thread
from typing import Any
from wsgiref.simple_server import WSGIServer

from prometheus_client import start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector, CollectorRegistry

from cast.errors import InvalidArgumentError

__all__ = ["MetricsEndpoint", "SnapshotCollector", "families", "serve_metrics"]

Snapshot = dict[str, Any]

# Counters of a component and of a WM: JSON name -> (metric name without prefix, help).
_COUNTERS = {
    "reads": ("reads", "read calls answered (Get, GetByType, Exists)"),
    "entries_read": ("entries_read", "entries returned by reads"),
    "writes_refused": ("writes_refused", "write and batch calls refused (nothing applied)"),
    "bytes_in": ("bytes_in", "bytes of values written"),
    "bytes_out": ("bytes_out", "bytes of values returned by reads and carried by events"),
    "events": ("events", "change events delivered to watchers"),
    "event_bytes": ("event_bytes", "bytes of values carried by the events delivered"),
    "locks": ("locks", "locks taken (re-entries included)"),
    "lock_waits": ("lock_waits", "lock calls that waited for another holder"),
    "lock_wait_s": ("lock_wait_seconds", "time lock calls waited for another holder"),
    "task_wait_s": ("task_wait_seconds", "time from proposal to adoption, summed over adopted tasks"),
}
_OPERATIONS = {"adds": "add", "overwrites": "overwrite", "deletes": "delete"}
_TASK_STATES = ("proposed", "adopted", "rejected", "retracted", "completed")
_TRAFFIC = ("reads", "writes", "bytes_in", "bytes_out", "events")


def _buckets(counts: Sequence[int], bounds: Sequence[float]) -> list[tuple[str, float]]:
    """Per-bucket counts as Prometheus's cumulative ``le`` buckets, ``+Inf`` last."""
    out: list[tuple[str, float]] = []
    running = 0
    for bound, n in zip([*bounds, None], counts, strict=True):
        running += n
        out.append(("+Inf" if bound is None else repr(float(bound)), running))
    return out


def _counter_families(prefix: str, what: str, labels: list[str], rows: list[tuple[list[str], dict[str, Any]]],
                      refused: bool) -> Iterator[Metric]:
    for key, (name, help_text) in _COUNTERS.items():
        if key == "writes_refused" and not refused:
            continue
        family = CounterMetricFamily(f"{prefix}_{name}", f"{help_text}, {what}", labels=labels)
        for values, counters in rows:
            family.add_metric(values, counters[key])
        yield family
    writes = CounterMetricFamily(f"{prefix}_writes", f"writes applied by operation (a batch operation is one), {what}",
                                 labels=[*labels, "operation"])
    tasks = CounterMetricFamily(f"{prefix}_tasks", f"tasks by what happened to them, {what}", labels=[*labels, "state"])
    for values, counters in rows:
        for key, operation in _OPERATIONS.items():
            writes.add_metric([*values, operation], counters[key])
        for state in _TASK_STATES:
            tasks.add_metric([*values, state], counters[f"tasks_{state}"])
    yield writes
    yield tasks


def families(snap: Snapshot) -> Iterator[Metric]:
    """Every metric family of a snapshot."""
    bounds = snap["buckets_s"]
    enabled = GaugeMetricFamily("cast_metrics_enabled", "1 if the server counts (not --no-metrics)", labels=["system"])
    enabled.add_metric([snap["system"]], 1 if snap["enabled"] else 0)
    yield enabled
    yield GaugeMetricFamily("cast_uptime_seconds", "how long the server has counted", value=snap["uptime_s"])
    comps = [([cid, c["subarchitecture"]], c) for cid, c in snap["components"].items()]
    yield from _counter_families("cast_component", "per component", ["component", "subarchitecture"], comps, True)
    wms = [([sa], c) for sa, c in snap["subarchitectures"].items()]
    yield from _counter_families("cast_wm", "per working memory (calls into it)", ["subarchitecture"], wms, False)
    waits = HistogramMetricFamily("cast_task_wait_seconds", "time from a task's proposal to its adoption",
                                  labels=["subarchitecture"])
    for sa, c in snap["subarchitectures"].items():
        waits.add_metric([sa], _buckets(c["task_wait"]["buckets"], bounds), c["task_wait"]["sum_s"])
    yield waits
    for name in _TRAFFIC:
        traffic = CounterMetricFamily(f"cast_traffic_{name}", f"{name} from components of from_sa into the WM of "
                                      "to_sa (events: of to_sa's WM, to watchers of from_sa)",
                                      labels=["from_sa", "to_sa"])
        for cell in snap["traffic"]:
            traffic.add_metric([cell["from_sa"], cell["to_sa"]], cell[name])
        yield traffic
    latency = HistogramMetricFamily("cast_event_delivery_latency_seconds", "write -> event delivery latency per "
                                    "watcher: from the write's commit to the event handed to its stream",
                                    labels=["component", "subarchitecture"])
    for watcher, hist in snap["delivery_latency"]["watchers"].items():
        latency.add_metric([watcher, hist["subarchitecture"]], _buckets(hist["buckets"], bounds), hist["sum_s"])
    yield latency
    count = CounterMetricFamily("cast_report_count", "values reported by components", labels=["component", "name"])
    gauges = {key: GaugeMetricFamily(f"cast_report_{key}", f"the {key} of the values reported",
                                     labels=["component", "name"]) for key in ("sum", "min", "max", "last")}
    for cid, named in snap["reports"].items():
        for name, r in named.items():
            count.add_metric([cid, name], r["count"])
            for key, gauge in gauges.items():
                gauge.add_metric([cid, name], r[key])
    yield count
    yield from gauges.values()


class SnapshotCollector(Collector):
    """Collects the families of whatever ``snapshot()`` returns at scrape time."""

    def __init__(self, snapshot: Callable[[], Snapshot]) -> None:
        self._snapshot = snapshot

    def collect(self) -> Iterator[Metric]:
        """The families of a fresh snapshot."""
        return families(self._snapshot())


@dataclass
class MetricsEndpoint:
    """A running /metrics HTTP server (on its own daemon thread)."""

    httpd: WSGIServer
    thread: Thread

    @property
    def address(self) -> str:
        """``host:port`` it is bound to (the port chosen when asked for port 0)."""
        host, port = self.httpd.server_address[:2]
        return f"{host.decode() if isinstance(host, bytes) else host}:{port}"

    def close(self) -> None:
        """Stop serving and free the port."""
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(5)


def serve_metrics(listen: str, snapshot: Callable[[], Snapshot]) -> MetricsEndpoint:
    """Serve ``snapshot()`` as Prometheus text on ``http://HOST:PORT/metrics`` (port 0 picks a free one)."""
    host, sep, port = listen.rpartition(":")
    if not sep or not port.isdigit():
        raise InvalidArgumentError(f"metrics address '{listen}' must be HOST:PORT (port 0 picks a free port)")
    registry = CollectorRegistry()
    registry.register(SnapshotCollector(snapshot))
    httpd, thread = start_http_server(int(port), host or "0.0.0.0", registry)
    return MetricsEndpoint(httpd, thread)
