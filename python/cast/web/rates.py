"""Rates over the last minute from successive samples of the servers' counters: plain arithmetic, no I/O.

Every tick the view takes a :class:`Sample`: each WM's revision (one per
change, so its growth is the SA's events per second) and the merged metrics
of every server (``Inspection.GetMetrics``). Differences between samples give
the rates the page draws: events/s per SA, the write -> event delivery latency
of the events delivered in each interval (quantiles of the histogram's growth,
as Prometheus's ``histogram_quantile`` over ``rate()``), and the cross-SA
traffic of the last few seconds. A counter that went down (a server restarted
and counts from 0 again) counts as no change for that interval.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

from cast.core.metrics_view import quantile

__all__ = ["TRAFFIC_WINDOW_S", "WINDOW_S", "RateWindow", "Sample"]

WINDOW_S = 60.0
"""How far back the charts go."""
TRAFFIC_WINDOW_S = 5.0
"""The arrows' traffic is the rate over about this long."""


@dataclass(frozen=True)
class Sample:
    """The counters at one moment: monotonic time, each SA's revision, the merged metrics."""

    at: float
    revisions: dict[str, int]
    metrics: dict[str, Any]


def _grown(new: int | float, old: int | float) -> float:
    return float(new - old) if new >= old else 0.0


def _buckets(sample: Sample) -> list[int]:
    return list(sample.metrics["delivery_latency"]["all"]["buckets"])


def _cells(sample: Sample) -> dict[tuple[str, str], dict[str, Any]]:
    return {(c["from_sa"], c["to_sa"]): c for c in sample.metrics["traffic"]}


class RateWindow:
    """The samples of the last :data:`WINDOW_S` seconds and the rates between them."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self._window = window_s
        self._samples: deque[Sample] = deque()

    def add(self, sample: Sample) -> None:
        """Take a sample (times must grow); samples older than the window (but the one just before it) go."""
        self._samples.append(sample)
        while len(self._samples) > 2 and sample.at - self._samples[1].at >= self._window:
            self._samples.popleft()

    def _pairs(self) -> list[tuple[Sample, Sample]]:
        return [(a, b) for a, b in pairwise(self._samples) if b.at > a.at]

    def events_per_s(self) -> dict[str, list[list[float]]]:
        """Per SA, ``[seconds before now, events/s]`` for each interval of the window, oldest first."""
        if not self._samples:
            return {}
        now = self._samples[-1].at
        out: dict[str, list[list[float]]] = {sa: [] for sa in self._samples[-1].revisions}
        for a, b in self._pairs():
            for sa, series in out.items():
                if sa in a.revisions and sa in b.revisions:
                    series.append([round(b.at - now, 3), _grown(b.revisions[sa], a.revisions[sa]) / (b.at - a.at)])
        return out

    def latency(self) -> list[dict[str, Any]]:
        """For each interval: ``t`` (seconds before now), how many events were delivered, and p50 / p90 (seconds).

        The quantiles are None for an interval in which nothing was delivered.
        """
        if not self._samples:
            return []
        now = self._samples[-1].at
        bounds = self._samples[-1].metrics["buckets_s"]
        out: list[dict[str, Any]] = []
        for a, b in self._pairs():
            old, new = _buckets(a), _buckets(b)
            grown = [max(0, y - x) for x, y in zip(old, new, strict=True)] if len(old) == len(new) else new
            count = sum(grown)
            out.append({"t": round(b.at - now, 3), "count": count,
                        "p50_s": quantile(grown, bounds, 0.5) if count else None,
                        "p90_s": quantile(grown, bounds, 0.9) if count else None})
        return out

    def _recent(self) -> list[tuple[str, str, dict[str, Any], dict[str, float]]]:
        """Each traffic cell now, with its reads, writes and events per second over the last few seconds."""
        if not self._samples:
            return []
        last = self._samples[-1]
        first = next((s for s in reversed(self._samples) if last.at - s.at >= TRAFFIC_WINDOW_S), self._samples[0])
        span = last.at - first.at
        before = _cells(first)
        out = []
        for (from_sa, to_sa), cell in sorted(_cells(last).items()):
            old = before.get((from_sa, to_sa), {})
            rates = {f"{name}_per_s": (_grown(cell[name], old.get(name, 0)) / span if span > 0 else 0.0)
                     for name in ("reads", "writes", "events")}
            out.append((from_sa, to_sa, cell, rates))
        return out

    def traffic(self) -> list[dict[str, Any]]:
        """Per pair of different SAs that ever had traffic: reads, writes and events per second lately, and totals.

        Callers of no SA (tools, scripts, this view) are left out: they are
        not part of the architecture.
        """
        return [{"from": from_sa, "to": to_sa, **rates, "reads": cell["reads"], "writes": cell["writes"],
                 "events": cell["events"]}
                for from_sa, to_sa, cell, rates in self._recent() if from_sa and from_sa != to_sa]

    def within(self) -> dict[str, dict[str, float]]:
        """Per SA, the calls per second of its own components into its own WM lately."""
        return {from_sa: rates for from_sa, to_sa, _cell, rates in self._recent() if from_sa and from_sa == to_sa}
