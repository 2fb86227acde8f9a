"""The numbers a sweep compares, taken from one run's summary, and their spread over repeats.

A run's summary is ``cast run --summary-json``: components, SAs (revisions and
task counters) and, from servers that keep them, ``metrics``
(docs/experiments.md, "Metrics"). Each measure is a number per run, or None
when the run does not have it (its server keeps no metrics, say); a variant's
value is the median over its repeats with the smallest and largest beside it.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["MEASURES", "Measure", "Spread", "reports", "spread", "traffic"]

Summary = dict[str, Any]


@dataclass(frozen=True)
class Measure:
    """One column of the report: its name, unit and how to read it from a run."""

    key: str
    title: str
    unit: str
    read: Callable[[Summary, float], float | None]


@dataclass(frozen=True)
class Spread:
    """A variant's value over its repeats: median, smallest, largest, how many runs had it."""

    median: float
    low: float
    high: float
    n: int

    def text(self, digits: int | None = None) -> str:
        """``median [low, high]``, or the one value; ``digits`` after the point, else three significant ones."""
        def number(x: float) -> str:
            if digits is not None:
                return f"{x:.{digits}f}"
            return f"{x:.0f}" if abs(x) >= 100 else f"{x:.3g}"  # 7.31, 60.9, 1234; 0.0123 not 0.0
        if self.n == 1 or self.low == self.high:
            return number(self.median)
        return f"{number(self.median)} [{number(self.low)}, {number(self.high)}]"


def spread(values: Iterable[float | None]) -> Spread | None:
    """The spread of the values that exist; None if none does."""
    present = [v for v in values if v is not None]
    if not present:
        return None
    return Spread(statistics.median(present), min(present), max(present), len(present))


def _metrics(summary: Summary) -> dict[str, Any]:
    found = summary.get("metrics")
    return found if isinstance(found, dict) else {}


def _events_per_s(summary: Summary, seconds: float) -> float | None:
    """Changes committed in every SA, per second of the run's measured window (``--for``)."""
    sas = summary.get("subarchitectures") or []
    if not sas or seconds <= 0:
        return None
    return sum(int(sa.get("revision", 0)) for sa in sas) / seconds


def _task_counter(name: str) -> Callable[[Summary, float], float | None]:
    def read(summary: Summary, seconds: float) -> float | None:
        sas = summary.get("subarchitectures") or []
        return float(sum(int(sa.get("counters", {}).get(name, 0)) for sa in sas)) if sas else None
    return read


def _latency(quantile: str) -> Callable[[Summary, float], float | None]:
    """The write -> event delivery latency of all watchers together, in milliseconds."""
    def read(summary: Summary, seconds: float) -> float | None:
        overall = _metrics(summary).get("delivery_latency", {}).get("all", {})
        value = overall.get(quantile)
        return float(value) * 1000 if isinstance(value, int | float) else None
    return read


def _task_wait(summary: Summary, seconds: float) -> float | None:
    """Median time from a task's proposal to its adoption, over every SA, in milliseconds."""
    waits = [sa.get("task_wait", {}) for sa in _metrics(summary).get("subarchitectures", {}).values()]
    counted = [(w.get("count", 0), w.get("sum_s", 0.0)) for w in waits if w.get("count")]
    if not counted:
        return None
    return 1000 * float(sum(s for _, s in counted)) / float(sum(c for c, _ in counted))


MEASURES: Sequence[Measure] = (
    Measure("events_per_s", "throughput", "changes/s", _events_per_s),
    Measure("latency_p50_ms", "latency p50", "ms", _latency("p50_s")),
    Measure("latency_p95_ms", "latency p95", "ms", _latency("p95_s")),
    Measure("task_wait_ms", "task wait (mean)", "ms", _task_wait),
    Measure("tasks_completed", "tasks completed", "tasks", _task_counter("completed")),
    Measure("tasks_rejected", "tasks rejected", "tasks", _task_counter("rejected")),
)


def traffic(summary: Summary) -> dict[tuple[str, str], float]:
    """The cross-SA traffic matrix: (from SA, to SA) -> reads + writes."""
    cells: dict[tuple[str, str], float] = {}
    for cell in _metrics(summary).get("traffic", []):
        # SA "" is a tool's or script's that belongs to no SA, "(none)" as in `cast stats`.
        key = (str(cell.get("from_sa", "")) or "(none)", str(cell.get("to_sa", "")) or "(none)")
        cells[key] = cells.get(key, 0.0) + float(cell.get("reads", 0)) + float(cell.get("writes", 0))
    return cells


def reports(summary: Summary) -> dict[str, float]:
    """Component-reported outcomes (``report(name, value)``), per name over every component of the run.

    Two figures per name: ``NAME sum`` (a count, such as questions answered, adds up) and ``NAME mean``
    (a duration or a score, such as the time to an answer, averages).
    """
    totals: dict[str, tuple[float, int]] = {}
    for per_component in _metrics(summary).get("reports", {}).values():
        for name, agg in per_component.items():
            total, count = totals.get(name, (0.0, 0))
            totals[name] = (total + float(agg.get("sum", 0.0)), count + int(agg.get("count", 0)))
    out: dict[str, float] = {}
    for name, (total, count) in totals.items():
        out[f"{name} sum"] = total
        if count:
            out[f"{name} mean"] = total / count
    return out
