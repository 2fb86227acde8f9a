"""Outcomes components report (``report("answers_correct", 1)``), kept per (component, name).

The store behind ``Component.report``: the wire call takes the identity from the
token, calls :meth:`Reports.report` and maps its errors; the aggregates are in
the metrics' JSON and Prometheus output (docs/experiments.md, "Metrics").
"""

from __future__ import annotations

import math
import time
from typing import Any

from cast.errors import InvalidArgumentError, ResourceExhaustedError

__all__ = ["MAX_REPORT_NAMES", "Reports"]

MAX_REPORT_NAMES = 256
"""Distinct report names one component may use (what it reports is kept for the server's life)."""


class _Report:
    """One named outcome of one component: count, sum, min, max, last and when it came."""

    __slots__ = ("count", "last", "last_ns", "max", "min", "sum")

    def __init__(self, value: float, now_ns: int) -> None:
        self.count, self.sum, self.min, self.max, self.last, self.last_ns = 1, value, value, value, value, now_ns


class Reports:
    """Count, sum, min, max and the last value of every (component, name) reported."""

    def __init__(self) -> None:
        self._reports: dict[str, dict[str, _Report]] = {}

    def report(self, component_id: str, name: str, value: float) -> None:
        """Record one value of ``name`` for ``component_id``.

        INVALID_ARGUMENT for an empty or over-long name (128 bytes) or a value
        that is not a finite number; RESOURCE_EXHAUSTED past
        :data:`MAX_REPORT_NAMES` names for one component.
        """
        if not name or len(name.encode()) > 128:
            raise InvalidArgumentError(f"a report name must be 1 to 128 bytes, got {name!r}")
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise InvalidArgumentError(f"report '{name}': the value must be a number, got {value!r}") from None
        if not math.isfinite(value):
            raise InvalidArgumentError(f"report '{name}': the value must be a finite number, got {value}")
        mine = self._reports.setdefault(component_id, {})
        found = mine.get(name)
        now = time.time_ns()
        if found is None:
            if len(mine) >= MAX_REPORT_NAMES:
                raise ResourceExhaustedError(
                    f"component '{component_id}' already reports {len(mine)} names, the limit: report fewer "
                    "names (a name is a measure; put the variation in its value)"
                )
            mine.setdefault(name, _Report(value, now))
            return
        found.count += 1
        found.sum += value
        found.min = min(found.min, value)
        found.max = max(found.max, value)
        found.last, found.last_ns = value, now

    def snapshot(self) -> dict[str, dict[str, dict[str, Any]]]:
        """By component, then name: count, sum, min, max, last, mean and last_time (Unix seconds)."""
        return {cid: {name: {"count": r.count, "sum": r.sum, "min": r.min, "max": r.max, "last": r.last,
                             "mean": r.sum / r.count, "last_time": r.last_ns / 1e9}
                      for name, r in sorted(dict(named).items())}
                for cid, named in sorted(dict(self._reports).items())}
