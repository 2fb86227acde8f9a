"""What every caller does, counted in the core so that every transport counts alike.

One :class:`Metrics` per :class:`cast.core.system.System`. The rulebook
(:mod:`cast.core.access`) feeds it the calls it answers and the events it hands
to watchers, the task board (:mod:`cast.core.tasks`) its decisions. From that
come, per component, per working memory and per pair of SAs (the caller's
registered SA -> the WM's SA): reads, writes by operation, bytes, events
delivered, lock waits and tasks; the write -> event delivery latency per
watcher, as a histogram; and the outcomes components report
(:mod:`cast.core.reports`). Every figure and its unit: docs/experiments.md,
"Metrics"; the JSON shape: :mod:`cast.core.metrics_view`.

Cheap enough to be always on. A call updates one record: what one component
did to one WM (:class:`Counts`), or what one watcher was sent
(:class:`Watching`); the totals per component, per WM and per pair of SAs are
added up when a snapshot is taken. No lock of its own: every count is an
integer increment of a slot or a list item with no call in between, and
CPython (3.11 on) hands the GIL to another thread only at calls and backward
jumps, so the event loop and in-process components' threads do not lose each
other's increments; records are created with ``dict.setdefault`` (atomic). A
snapshot copies the tables (C-level copies) and then reads the slots: at worst
a call or two behind.
"""

from __future__ import annotations

import time
from bisect import bisect_left
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from cast.core.metrics_view import COUNTERS, histogram_json
from cast.core.records import BatchOp, Identity, Operation
from cast.core.reports import Reports
from cast.core.watch import Match, Subscription

__all__ = ["BUCKETS_S", "Counts", "Histogram", "Metrics", "Watching"]

BUCKETS_S = (0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
             1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0)
"""Upper bounds (seconds) of the histograms' buckets; one more bucket counts what is above the last."""

_BUCKETS_NS = tuple(round(b * 1e9) for b in BUCKETS_S)
_ADD, _OVERWRITE = Operation.ADD, Operation.OVERWRITE
_SUMMED = ("reads", "entries_read", "adds", "overwrites", "deletes", "bytes_in", "bytes_out", "locks", "lock_waits",
           "lock_wait_ns", "tasks_proposed", "tasks_adopted", "tasks_rejected", "tasks_retracted",
           "tasks_completed", "task_wait_ns")


class Counts:
    """What one component did to one working memory (and, added up, a component's or a WM's totals)."""

    __slots__ = _SUMMED

    def __init__(self) -> None:
        self.reads = self.entries_read = self.bytes_out = 0
        self.adds = self.overwrites = self.deletes = self.bytes_in = 0
        self.locks = self.lock_waits = self.lock_wait_ns = 0
        self.tasks_proposed = self.tasks_adopted = self.tasks_rejected = self.tasks_retracted = 0
        self.tasks_completed = self.task_wait_ns = 0

    def add(self, other: Counts) -> None:
        """Add ``other``'s counts to these."""
        for name in _SUMMED:
            setattr(self, name, getattr(self, name) + getattr(other, name))


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


class Watching:
    """What one watcher (a component, all its streams) was sent: the latency histogram, events per WM."""

    __slots__ = ("by_sa", "latency", "subarchitecture")

    def __init__(self, subarchitecture: str) -> None:
        self.subarchitecture = subarchitecture
        self.latency = Histogram()
        self.by_sa: dict[str, list[int]] = {}  # SA of the events -> [events, bytes of the values they carried]



def _count_write(c: Counts, op: BatchOp) -> None:
    """One applied write in ``c``: by its operation, and the bytes of its value."""
    kind = op.operation
    if kind is _ADD:
        c.adds += 1
    elif kind is _OVERWRITE:
        c.overwrites += 1
    else:
        c.deletes += 1
    c.bytes_in += len(op.data)

class Metrics:
    """The counters of one server: fed by the rulebook and the task board, read by :meth:`snapshot`."""

    def __init__(self, system: str, subarchitectures: Iterable[str], enabled: bool = True,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self.system = system
        self.enabled = enabled
        self.reports = Reports()  # kept whether or not counting is on: reporting is the component's own call
        self._clock = clock  # the clock of the events' times (cast.core.host stamps them with time.time_ns)
        self._started = time.monotonic()
        self._sas = tuple(subarchitectures)
        self._usage: dict[str, dict[str, Counts]] = {}  # component -> WM's SA -> what it did there
        self._registered: dict[str, str] = {}  # component -> its registered SA (as first seen)
        self._refused: dict[str, list[int]] = {}  # component -> [writes refused]
        self._watching: dict[str, Watching] = {}
        self._task_waits: dict[str, Histogram] = {sa: Histogram() for sa in self._sas}
        # The shared memory's own state (cast.core.shared.SharedMemory.snapshot), when the server keeps one.
        self.shared: Callable[[], dict[str, int]] | None = None

    @property
    def active(self) -> Metrics | None:
        """This object when counting is on, else None (what the feeders test, once per call)."""
        return self if self.enabled else None

    def report(self, component_id: str, name: str, value: float) -> None:
        """Record an outcome a component reports (:meth:`cast.core.reports.Reports.report`)."""
        self.reports.report(component_id, name, value)

    # ------------------------------------------------------------- feeding
    # Run on every call: one record looked up, plain increments.

    def _counts(self, component_id: str, sa: str, registered: str) -> Counts:
        """The record of what ``component_id`` did to ``sa``'s WM, made on first use."""
        mine = self._usage.get(component_id)
        if mine is None:
            self._registered.setdefault(component_id, registered)
            mine = self._usage.setdefault(component_id, {})
        counts = mine.get(sa)
        return counts if counts is not None else mine.setdefault(sa, Counts())

    def read(self, who: Identity, sa: str, entries: int, size: int) -> None:
        """A read call answered: ``entries`` returned with ``size`` bytes of values (0 and 0 for Exists)."""
        c = self._counts(who.component_id, sa, who.subarchitecture)
        c.reads += 1
        c.entries_read += entries
        c.bytes_out += size

    def wrote(self, who: Identity, op: BatchOp) -> None:
        """One write applied."""
        _count_write(self._counts(who.component_id, op.subarchitecture, who.subarchitecture), op)

    def wrote_batch(self, who: Identity, ops: Sequence[BatchOp]) -> None:
        """The writes of a batch applied, each counted as one write."""
        c: Counts | None = None
        sa = None
        for op in ops:
            if op.subarchitecture != sa:  # a batch is mostly of one WM: look its record up once
                sa = op.subarchitecture
                c = self._counts(who.component_id, sa, who.subarchitecture)
            assert c is not None
            _count_write(c, op)

    def refused(self, who: Identity) -> None:
        """A write or batch refused (conflict, lock, permission, limit...): nothing was applied."""
        mine = self._refused.get(who.component_id)
        if mine is None:
            self._registered.setdefault(who.component_id, who.subarchitecture)
            mine = self._refused.setdefault(who.component_id, [0])
        mine[0] += 1

    def delivered(self, who: Identity, sub: Subscription, matches: Sequence[Match],
                  carries: Callable[[Match], bool]) -> None:
        """Events handed to the watcher ``who``: ``matches``, what ``sub`` just polled.

        The latency of each is from its commit (the event's time, stamped as
        the write is numbered) to now, when the rulebook hands it over.
        ``carries`` (the rulebook's say, ODR locks) tells which go with their
        entry's value; asked only when a watch of ``sub`` asks for values. A
        watcher may be sent tens of thousands of events a second, so nothing
        here looks at each event in Python but the values' bytes.
        """
        now = self._clock()
        watching = self._watching.get(who.component_id)
        if watching is None:
            self._registered.setdefault(who.component_id, who.subarchitecture)
            watching = self._watching.setdefault(who.component_id, Watching(who.subarchitecture))
        if len(matches) == 1:
            watching.latency.observe(now - matches[0].event.time_ns)
        else:
            _observe_times(watching.latency, [m.event.time_ns for m in matches], now)
        by_sa = watching.by_sa
        for sa, events in sub.polled:
            tally = by_sa.get(sa)
            if tally is None:
                tally = by_sa.setdefault(sa, [0, 0])
            tally[0] += events
        if sub.with_values:
            for m in matches:
                ev = m.event
                if m.include_entry and ev.entry is not None and carries(m):
                    by_sa[ev.subarchitecture][1] += len(ev.entry.data)

    def locked(self, who: Identity, sa: str) -> None:
        """A lock taken (or re-entered)."""
        self._counts(who.component_id, sa, who.subarchitecture).locks += 1

    def lock_waited(self, who: Identity, sa: str, ns: int) -> None:
        """A lock call that had to wait, for ``ns`` nanoseconds, whether it got the lock or not."""
        c = self._counts(who.component_id, sa, who.subarchitecture)
        c.lock_waits += 1
        c.lock_wait_ns += ns

    def task(self, component_id: str, sa: str, what: str, wait_ns: int | None = None) -> None:
        """A task of ``component_id`` in ``sa`` was proposed, adopted, rejected, retracted or completed.

        ``wait_ns``, for an adoption: the time from its proposal.
        """
        c = self._counts(component_id, sa, sa)  # a component proposes to its own SA's task manager
        name = f"tasks_{what}"
        setattr(c, name, getattr(c, name) + 1)
        if wait_ns is not None:
            c.task_wait_ns += max(0, wait_ns)
            self._task_waits[sa].observe(wait_ns)

    # ------------------------------------------------------------- reading

    def snapshot(self) -> dict[str, Any]:
        """Everything counted so far, in the JSON shape of ``cast stats --json`` (cast.core.metrics_view)."""
        usage = {cid: dict(by_sa) for cid, by_sa in dict(self._usage).items()}
        registered = dict(self._registered)
        refused = {cid: n[0] for cid, n in dict(self._refused).items()}
        watching = dict(self._watching)
        per_component = {cid: Counts() for cid in registered}
        per_wm = {sa: Counts() for sa in self._sas}
        events = {cid: [0, 0] for cid in registered}  # component -> [events, bytes] it was sent
        wm_events = {sa: [0, 0] for sa in self._sas}
        cells: dict[tuple[str, str], dict[str, int]] = {}

        def cell(a: str, b: str) -> dict[str, int]:
            return cells.setdefault((a, b), {"reads": 0, "writes": 0, "bytes_in": 0, "bytes_out": 0, "events": 0})

        for cid, by_sa in usage.items():
            for sa, c in by_sa.items():
                per_component[cid].add(c)
                per_wm.setdefault(sa, Counts()).add(c)
                if c.reads or c.adds or c.overwrites or c.deletes:
                    t = cell(registered[cid], sa)
                    t["reads"] += c.reads
                    t["writes"] += c.adds + c.overwrites + c.deletes
                    t["bytes_in"] += c.bytes_in
                    t["bytes_out"] += c.bytes_out
        latency: dict[str, Any] = {}
        everyone = Histogram()
        for watcher, w in sorted(watching.items()):
            for sa, (n, size) in dict(w.by_sa).items():
                for tally in (events[watcher], wm_events.setdefault(sa, [0, 0])):
                    tally[0] += n
                    tally[1] += size
                t = cell(w.subarchitecture, sa)
                t["events"] += n
                t["bytes_out"] += size
            counts, total = list(w.latency.counts), w.latency.sum_ns
            everyone.counts = [a + b for a, b in zip(everyone.counts, counts, strict=True)]
            everyone.sum_ns += total
            latency[watcher] = {"subarchitecture": w.subarchitecture, **histogram_json(counts, total / 1e9, BUCKETS_S)}
        components = {cid: {"subarchitecture": registered[cid],
                            **_counters(per_component[cid], events[cid], refused.get(cid, 0))}
                      for cid in sorted(registered)}
        wms = {sa: {**_counters(c, wm_events[sa], None),
                    "task_wait": histogram_json(list(self._task_waits[sa].counts), self._task_waits[sa].sum_ns / 1e9,
                                                BUCKETS_S)}
               for sa, c in per_wm.items() if sa in self._task_waits}
        return {
            "enabled": self.enabled,
            "system": self.system,
            "servers": 1,
            "uptime_s": round(time.monotonic() - self._started, 3),
            "buckets_s": list(BUCKETS_S),
            "components": components,
            "subarchitectures": wms,
            "traffic": [{"from_sa": a, "to_sa": b, **t} for (a, b), t in sorted(cells.items())],
            "delivery_latency": {"all": histogram_json(everyone.counts, everyone.sum_ns / 1e9, BUCKETS_S),
                                 "watchers": latency},
            "reports": self.reports.snapshot(),
            "shared_memory": self.shared() if self.shared is not None else None,
        }


def _observe_times(hist: Histogram, times: list[int], now: int) -> None:
    """Count the latencies ``now - t`` of every commit time in ``times`` into ``hist``.

    With the times sorted, the events of a bucket are a run of them, found by
    bisection: a few C calls per batch instead of Python work per event. The
    times come in commit order, so sorting costs one pass; the order does not
    change the counts. A time after ``now`` (a clock step) counts as 0.
    """
    times.sort()
    k = len(times)
    counts, bounds = hist.counts, _BUCKETS_NS
    if times[-1] > now:
        for t in times:
            hist.observe(now - t)
        return
    hist.sum_ns += k * now - sum(times)
    low = bisect_left(bounds, now - times[-1])  # the newest event's bucket
    high = bisect_left(bounds, now - times[0])  # the oldest's
    counted = 0
    for j in range(low, high):
        within = k - bisect_left(times, now - bounds[j])  # latency <= bounds[j]: a time >= now - bounds[j]
        counts[j] += within - counted
        counted = within
    counts[high] += k - counted


def _counters(c: Counts, sent: list[int], refused: int | None) -> dict[str, Any]:
    """The counters of the JSON (COUNTERS' order) from summed counts and [events, bytes] sent."""
    values: dict[str, Any] = {
        "reads": c.reads, "entries_read": c.entries_read, "writes": c.adds + c.overwrites + c.deletes,
        "adds": c.adds, "overwrites": c.overwrites, "deletes": c.deletes, "writes_refused": refused,
        "bytes_in": c.bytes_in, "bytes_out": c.bytes_out + sent[1], "events": sent[0], "event_bytes": sent[1],
        "locks": c.locks, "lock_waits": c.lock_waits, "lock_wait_s": c.lock_wait_ns / 1e9,
        "tasks_proposed": c.tasks_proposed, "tasks_adopted": c.tasks_adopted, "tasks_rejected": c.tasks_rejected,
        "tasks_retracted": c.tasks_retracted, "tasks_completed": c.tasks_completed,
        "task_wait_s": c.task_wait_ns / 1e9,
    }
    return {name: values[name] for name in COUNTERS if name != "writes_refused" or refused is not None}
