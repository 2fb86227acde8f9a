"""What every caller does, counted in the core so that every transport counts alike.

One :class:`Metrics` per :class:`cast.core.system.System`. The rulebook
(:mod:`cast.core.access`) feeds it the calls it answers and the events it hands
to watchers, the task board (:mod:`cast.core.tasks`) its decisions. It counts
per component, per working memory and per pair of SAs (the caller's registered
SA -> the WM's SA): reads, writes by operation, bytes, events delivered, lock
waits and tasks; the write -> event delivery latency per watcher, as a
histogram; and the outcomes components report (:meth:`Metrics.report`). Every
figure and its unit: docs/experiments.md, "Metrics"; the JSON shape:
:mod:`cast.core.metrics_view`.

Cheap enough to be always on, so it takes no lock of its own: every count is
an integer increment of a slot or a list item with no call in between, and
CPython (3.11 on) hands the GIL to another thread only at calls and backward
jumps, so the event loop and in-process components' threads do not lose each
other's increments. A snapshot copies the tables (C-level copies, atomic under
the GIL) and then reads the slots: at worst a call or two behind.
"""

from __future__ import annotations

import math
import time
from bisect import bisect_left
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from cast.core.metrics_view import COUNTERS, histogram_json
from cast.core.records import BatchOp, Identity, Operation
from cast.core.watch import Match
from cast.errors import InvalidArgumentError, ResourceExhaustedError

__all__ = ["BUCKETS_S", "MAX_REPORT_NAMES", "Counts", "Histogram", "Metrics", "Traffic"]

BUCKETS_S = (0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
             1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0)
"""Upper bounds (seconds) of the histograms' buckets; one more bucket counts what is above the last."""

_BUCKETS_NS = tuple(round(b * 1e9) for b in BUCKETS_S)

MAX_REPORT_NAMES = 256
"""Distinct report names one component may use (what it reports is kept for the server's life)."""


class Counts:
    """The counters of one component, or of one working memory (the calls into it)."""

    __slots__ = ("adds", "bytes_in", "bytes_out", "deletes", "entries_read", "event_bytes", "events", "lock_wait_ns",
                 "lock_waits", "locks", "overwrites", "reads", "subarchitecture", "task_wait_ns", "tasks_adopted",
                 "tasks_completed", "tasks_proposed", "tasks_rejected", "tasks_retracted", "writes_refused")

    def __init__(self, subarchitecture: str = "") -> None:
        self.subarchitecture = subarchitecture  # a component's registered SA ("" for a WM's own counts)
        self.reads = self.entries_read = self.bytes_out = 0
        self.adds = self.overwrites = self.deletes = self.writes_refused = self.bytes_in = 0
        self.events = self.event_bytes = 0
        self.locks = self.lock_waits = self.lock_wait_ns = 0
        self.tasks_proposed = self.tasks_adopted = self.tasks_rejected = self.tasks_retracted = 0
        self.tasks_completed = self.task_wait_ns = 0

    def json(self, with_refused: bool) -> dict[str, Any]:
        """The counters as in ``cast stats --json`` (nanoseconds as seconds)."""
        out: dict[str, Any] = {}
        for name in COUNTERS:
            if name == "writes":
                out[name] = self.adds + self.overwrites + self.deletes
            elif name == "lock_wait_s":
                out[name] = self.lock_wait_ns / 1e9
            elif name == "task_wait_s":
                out[name] = self.task_wait_ns / 1e9
            elif name != "writes_refused" or with_refused:
                out[name] = getattr(self, name)
        return out


class Traffic:
    """One cell of the cross-SA matrix: what components of one SA did with the WM of another."""

    __slots__ = ("bytes_in", "bytes_out", "events", "reads", "writes")

    def __init__(self) -> None:
        self.reads = self.writes = self.bytes_in = self.bytes_out = self.events = 0


class Histogram:
    """Counts of durations per bucket of :data:`BUCKETS_S`, and their sum."""

    __slots__ = ("counts", "sum_ns")

    def __init__(self) -> None:
        self.counts = [0] * (len(_BUCKETS_NS) + 1)
        self.sum_ns = 0

    def observe(self, ns: int) -> None:
        """Count one duration (nanoseconds; a negative one, from a clock step, counts as 0)."""
        if ns < 0:
            ns = 0
        self.counts[bisect_left(_BUCKETS_NS, ns)] += 1  # bisect_left: a value equal to a bound is in its bucket
        self.sum_ns += ns


class _Report:
    """One named outcome of one component: count, sum, min, max, last and when it came."""

    __slots__ = ("count", "last", "last_ns", "max", "min", "sum")

    def __init__(self, value: float, now_ns: int) -> None:
        self.count, self.sum, self.min, self.max, self.last, self.last_ns = 1, value, value, value, value, now_ns


class Metrics:
    """The counters of one server: fed by the rulebook and the task board, read by :meth:`snapshot`."""

    def __init__(self, system: str, subarchitectures: Iterable[str], enabled: bool = True,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self.system = system
        self.enabled = enabled
        self._clock = clock  # the clock of the events' times (cast.core.host stamps them with time.time_ns)
        self._started = time.monotonic()
        self._components: dict[str, Counts] = {}
        self._wms: dict[str, Counts] = {sa: Counts() for sa in subarchitectures}
        self._task_waits: dict[str, Histogram] = {sa: Histogram() for sa in self._wms}
        self._traffic: dict[tuple[str, str], Traffic] = {}
        self._latency: dict[str, tuple[str, Histogram]] = {}  # watcher -> (its SA, histogram)
        self._reports: dict[str, dict[str, _Report]] = {}

    @property
    def active(self) -> Metrics | None:
        """This object when counting is on, else None (what the feeders test, once per call)."""
        return self if self.enabled else None

    # ------------------------------------------------------------- feeding

    def _component(self, who: Identity) -> Counts:
        counts = self._components.get(who.component_id)
        if counts is None:
            counts = self._components[who.component_id] = Counts(who.subarchitecture)
        return counts

    def _cell(self, from_sa: str, to_sa: str) -> Traffic:
        key = (from_sa, to_sa)
        cell = self._traffic.get(key)
        if cell is None:
            cell = self._traffic[key] = Traffic()
        return cell

    def read(self, who: Identity, sa: str, entries: int, size: int) -> None:
        """A read call answered: ``entries`` returned with ``size`` bytes of values (0 and 0 for Exists)."""
        c = self._component(who)
        c.reads += 1
        c.entries_read += entries
        c.bytes_out += size
        w = self._wms[sa]
        w.reads += 1
        w.entries_read += entries
        w.bytes_out += size
        t = self._cell(who.subarchitecture, sa)
        t.reads += 1
        t.bytes_out += size

    def wrote(self, who: Identity, op: BatchOp) -> None:
        """One write applied."""
        size = len(op.data)
        kind = op.operation
        for c in (self._component(who), self._wms[op.subarchitecture]):
            if kind is Operation.ADD:
                c.adds += 1
            elif kind is Operation.OVERWRITE:
                c.overwrites += 1
            else:
                c.deletes += 1
            c.bytes_in += size
        t = self._cell(who.subarchitecture, op.subarchitecture)
        t.writes += 1
        t.bytes_in += size

    def wrote_batch(self, who: Identity, ops: Sequence[BatchOp]) -> None:
        """The writes of a batch applied, each counted as one write."""
        per_sa: dict[str, list[int]] = {}  # SA -> [bytes, adds, overwrites, deletes] (index = Operation value)
        for op in ops:
            tally = per_sa.get(op.subarchitecture)
            if tally is None:
                tally = per_sa[op.subarchitecture] = [0, 0, 0, 0]
            tally[op.operation] += 1
            tally[0] += len(op.data)
        comp = self._component(who)
        for sa, (size, adds, overwrites, deletes) in per_sa.items():
            for c in (comp, self._wms[sa]):
                c.adds += adds
                c.overwrites += overwrites
                c.deletes += deletes
                c.bytes_in += size
            t = self._cell(who.subarchitecture, sa)
            t.writes += adds + overwrites + deletes
            t.bytes_in += size

    def refused(self, who: Identity) -> None:
        """A write or batch refused (conflict, lock, permission, limit...): nothing was applied."""
        self._component(who).writes_refused += 1

    def delivered(self, who: Identity, matches: Sequence[Match], carries: Callable[[Match], bool]) -> None:
        """Events handed to the watcher ``who``; ``carries`` says which go with their entry's value.

        The latency of each is from its commit (the event's time, stamped as
        the write is numbered) to now, when the rulebook hands it over.
        """
        now = self._clock()
        entry = self._latency.get(who.component_id)
        if entry is None:
            entry = self._latency[who.component_id] = (who.subarchitecture, Histogram())
        hist = entry[1]
        counts, bounds = hist.counts, _BUCKETS_NS
        wms = self._wms
        total_bytes = 0
        sa = ""
        wm: Counts | None = None
        cell: Traffic | None = None
        for m in matches:
            ev = m.event
            latency = now - ev.time_ns
            if latency < 0:
                latency = 0
            counts[bisect_left(bounds, latency)] += 1
            hist.sum_ns += latency
            size = len(ev.entry.data) if ev.entry is not None and carries(m) else 0
            if wm is None or ev.subarchitecture != sa:  # batches are mostly of one WM: look it up once
                sa = ev.subarchitecture
                wm = wms[sa]
                cell = self._cell(who.subarchitecture, sa)
            assert cell is not None
            wm.events += 1
            wm.event_bytes += size
            wm.bytes_out += size
            cell.events += 1
            cell.bytes_out += size
            total_bytes += size
        c = self._component(who)
        c.events += len(matches)
        c.event_bytes += total_bytes
        c.bytes_out += total_bytes

    def locked(self, who: Identity, sa: str) -> None:
        """A lock taken (or re-entered)."""
        self._component(who).locks += 1
        self._wms[sa].locks += 1

    def lock_waited(self, who: Identity, sa: str, ns: int) -> None:
        """A lock call that had to wait, for ``ns`` nanoseconds, whether it got the lock or not."""
        c = self._component(who)
        c.lock_waits += 1
        c.lock_wait_ns += ns
        w = self._wms.get(sa)
        if w is not None:
            w.lock_waits += 1
            w.lock_wait_ns += ns

    def task(self, component_id: str, sa: str, what: str, wait_ns: int | None = None) -> None:
        """A task of ``component_id`` in ``sa`` was proposed, adopted, rejected, retracted or completed.

        ``wait_ns``, for an adoption: the time from its proposal.
        """
        c = self._components.get(component_id)
        if c is None:
            c = self._components[component_id] = Counts(sa)
        name = f"tasks_{what}"
        for counts in (c, self._wms[sa]):
            setattr(counts, name, getattr(counts, name) + 1)
            if wait_ns is not None:
                counts.task_wait_ns += max(0, wait_ns)
        if wait_ns is not None:
            self._task_waits[sa].observe(wait_ns)

    def report(self, component_id: str, name: str, value: float) -> None:
        """Record an outcome a component reports (``report("answers_correct", 1)``).

        Kept per (component, name) as count, sum, min, max and the last value,
        for the server's life; recorded whether or not counting is on (it is
        the component's own call). INVALID_ARGUMENT for an empty or over-long
        name or a value that is not a finite number; RESOURCE_EXHAUSTED past
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
            mine[name] = _Report(value, now)
            return
        found.count += 1
        found.sum += value
        found.min = min(found.min, value)
        found.max = max(found.max, value)
        found.last, found.last_ns = value, now

    # ------------------------------------------------------------- reading

    def snapshot(self) -> dict[str, Any]:
        """Everything counted so far, in the JSON shape of ``cast stats --json`` (cast.core.metrics_view)."""
        components = dict(self._components)
        wms = dict(self._wms)
        traffic = dict(self._traffic)
        latency = dict(self._latency)
        reports = {cid: dict(named) for cid, named in dict(self._reports).items()}
        everyone = Histogram()
        watchers: dict[str, Any] = {}
        for watcher, (sa, hist) in sorted(latency.items()):
            counts, total = list(hist.counts), hist.sum_ns
            everyone.counts = [a + b for a, b in zip(everyone.counts, counts, strict=True)]
            everyone.sum_ns += total
            watchers[watcher] = {"subarchitecture": sa, **histogram_json(counts, total / 1e9, BUCKETS_S)}
        return {
            "enabled": self.enabled,
            "system": self.system,
            "servers": 1,
            "uptime_s": round(time.monotonic() - self._started, 3),
            "buckets_s": list(BUCKETS_S),
            "components": {cid: {"subarchitecture": c.subarchitecture, **c.json(with_refused=True)}
                           for cid, c in sorted(components.items())},
            "subarchitectures": {
                sa: {**w.json(with_refused=False),
                     "task_wait": histogram_json(list(self._task_waits[sa].counts),
                                                 self._task_waits[sa].sum_ns / 1e9, BUCKETS_S)}
                for sa, w in wms.items()
            },
            "traffic": [{"from_sa": a, "to_sa": b, "reads": t.reads, "writes": t.writes, "bytes_in": t.bytes_in,
                         "bytes_out": t.bytes_out, "events": t.events}
                        for (a, b), t in sorted(traffic.items())],
            "delivery_latency": {"all": histogram_json(everyone.counts, everyone.sum_ns / 1e9, BUCKETS_S),
                                 "watchers": watchers},
            "reports": {cid: {name: {"count": r.count, "sum": r.sum, "min": r.min, "max": r.max, "last": r.last,
                                     "mean": r.sum / r.count, "last_time": r.last_ns / 1e9}
                              for name, r in sorted(named.items())}
                        for cid, named in sorted(reports.items())},
        }
