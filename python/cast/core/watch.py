"""Watch cursors: several filtered watches reading the history rings of a host.

A :class:`Subscription` is one consumer's view (one gRPC Watch stream, or one
in-process component). It holds watches, each a set of filters with its own
next revision per WM, and :meth:`Subscription.poll` returns every event that
is pending for any of them, once, with the ids of the watches it matched, in
the order the host applied them.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from mypy_extensions import mypyc_attr

from cast.core.host import MemoryHost
from cast.core.records import ChangeEvent, Operation
from cast.errors import HistoryExpiredError, InvalidArgumentError, ResourceExhaustedError

__all__ = ["EventFilter", "Match", "Subscription"]


@mypyc_attr(allow_interpreted_subclasses=True)  # cast.client.filters.ChangeFilter
@dataclass(frozen=True)
class EventFilter:
    """Selects events: every set field must match; empty fields match anything."""

    operations: frozenset[Operation] = frozenset()
    type: str = ""
    id: str = ""
    subarchitecture: str = ""
    source_component: str = ""
    source_subarchitecture: str = ""
    include_entry: bool = False

    def matches(self, ev: ChangeEvent) -> bool:
        """Whether ``ev`` passes this filter."""
        return (
            (not self.operations or ev.operation in self.operations)
            and (not self.type or ev.type == self.type)
            and (not self.id or ev.id == self.id)
            and (not self.subarchitecture or ev.subarchitecture == self.subarchitecture)
            and (not self.source_component or ev.source_component == self.source_component)
            and (not self.source_subarchitecture or ev.source_subarchitecture == self.source_subarchitecture)
        )


class Match:
    """An event pending for a subscription, the watches it matched, and whether to send its entry."""

    __slots__ = ("event", "first_skipped", "include_entry", "skipped", "watch_ids")

    def __init__(self, event: ChangeEvent, watch_ids: list[int], include_entry: bool) -> None:
        self.event = event
        self.watch_ids = watch_ids
        self.include_entry = include_entry
        # Earlier changes of the entry this one replaced for latest-delivery watches, and the oldest's revision.
        self.skipped = 0
        self.first_skipped = 0

    def replaces(self, older: Match) -> None:
        """This newer change of the entry takes ``older``'s place: it counts ``older`` and what it replaced."""
        self.skipped = older.skipped + 1
        self.first_skipped = older.first_skipped or older.event.revision


@dataclass
class _Watch:
    watch_id: int
    filters: tuple[EventFilter, ...]
    sas: frozenset[str]  # the WMs its filters can match
    next: dict[str, int] = field(default_factory=dict)
    latest: bool = False  # delivery "latest": pending changes of one entry conflate to the newest


def _matched(ev: ChangeEvent, sa: str, watches: Sequence[_Watch]) -> tuple[list[int], bool]:
    """The ids of the watches ``ev`` is pending for and matches, and whether any of them asks for its entry."""
    ids: list[int] = []
    include = False
    for w in watches:
        if ev.revision < w.next[sa]:
            continue
        for i, f in enumerate(w.filters):
            if f.matches(ev):
                ids.append(w.watch_id)
                # Any matching filter that asks for the entry gets it, not only the first.
                include = include or f.include_entry or any(
                    g.include_entry and g.matches(ev) for g in w.filters[i + 1:]
                )
                break
    return ids, include


def _seq(m: Match) -> int:
    return m.event.seq


def _within(batch: list[Match], max_events: int, max_bytes: int) -> bool:
    """Whether ``batch`` keeps a poll's bounds: as :meth:`Subscription.poll`, only its last match may pass them."""
    events, size = max_events, max_bytes
    for i, m in enumerate(batch):
        if i and ((max_events and events <= 0) or (max_bytes and size <= 0)):
            return False
        if max_events:
            events -= 1
        if max_bytes and m.include_entry and m.event.entry is not None:
            size -= len(m.event.entry.data)
    return True


class Subscription:
    """One consumer's watches over a host; not thread-safe (one consumer at a time)."""

    def __init__(self, host: MemoryHost, wake: Callable[[], None]) -> None:
        limit = host.limits.max_watchers
        if host.listener_count() >= limit:
            raise ResourceExhaustedError(
                f"this server already has {host.listener_count()} watchers, the limit (limits.max_watchers = "
                f"{limit}): share one watch stream between filters, or raise the limit"
            )
        self._host = host
        self._wake = wake
        self._watches: dict[int, _Watch] = {}
        # The watches of each WM, WMs in name order: poll runs on every write a consumer
        # watches (on the writer's thread in process), watches change rarely.
        self._by_sa: dict[str, list[_Watch]] | None = None
        self.behind = False  # the last poll stopped at its budget with events left
        # What the last poll returned per WM, (SA, events) in the order polled, and whether a watch asked
        # for values (it stays true once one did): the metrics count per WM without looking at each event
        # (cast.core.metrics).
        self.polled: list[tuple[str, int]] = []
        self.with_values = False
        # Changes taken for latest watches while the consumer could not be sent to (hold_latest): one per
        # entry and set of watches, newest wins; delivered by the next polls, in the host's order.
        self._held: dict[tuple[str, str, tuple[int, ...]], Match] = {}
        host.add_listener(wake)

    @property
    def watch_ids(self) -> list[int]:
        """Ids of the live watches."""
        return list(self._watches)

    def add_watch(
        self,
        watch_id: int,
        filters: Sequence[EventFilter],
        start_revisions: Mapping[str, int] | None = None,
        latest: bool = False,
    ) -> dict[str, int]:
        """Add a watch; return every WM's current revision.

        ``start_revisions`` maps an SA to the first revision to deliver; other
        SAs start after their current revision. HistoryExpiredError if a start
        is older than the history, INVALID_ARGUMENT if it is in the future.
        ``latest``: of the changes of one entry pending at a poll, deliver only
        the newest, counting the others in its :attr:`Match.skipped` (for fast
        data read by slower consumers: what piles up while the consumer is
        behind is one change per entry, never a queue).
        """
        if watch_id in self._watches:
            raise InvalidArgumentError(f"watch id {watch_id} is already in use on this stream: pick another")
        if not filters:
            raise InvalidArgumentError("a watch needs at least one filter (an empty filter matches everything)")
        all_sas = self._host.subarchitectures
        sas: set[str] = set()
        for f in filters:
            if f.subarchitecture:
                if f.subarchitecture not in all_sas:
                    self._host.revision(f.subarchitecture)  # raises the NOT_FOUND with the known SAs
                sas.add(f.subarchitecture)
            else:
                sas.update(all_sas)
        revisions = self._host.revisions()
        starts = dict(start_revisions or {})
        for sa, start in starts.items():
            if sa not in revisions:
                self._host.revision(sa)
            if start > revisions[sa] + 1:
                raise InvalidArgumentError(
                    f"start revision {start} for subarchitecture '{sa}' is in the future (current revision is "
                    f"{revisions[sa]})"
                )
            if start < 1:
                raise InvalidArgumentError(f"start revision for subarchitecture '{sa}' must be >= 1, got {start}")
            self._host.events_since(sa, start)  # raises HistoryExpiredError if too old
        nxt = {sa: starts.get(sa, revisions[sa] + 1) for sa in sas}
        self._watches[watch_id] = _Watch(watch_id, tuple(filters), frozenset(sas), nxt, latest)
        self._by_sa = None
        self.with_values = self.with_values or any(f.include_entry for f in filters)
        if starts:
            self._wake()  # history to replay
        return revisions

    def cancel(self, watch_id: int) -> bool:
        """Remove a watch; False if there was none with that id."""
        self._by_sa = None
        return self._watches.pop(watch_id, None) is not None

    @property
    def has_latest(self) -> bool:
        """Whether a watch of this subscription delivers ``latest`` (:meth:`hold_latest` has work to do)."""
        return any(w.latest for w in self._watches.values())

    def hold_latest(self) -> None:
        """Take the changes pending for this subscription's ``latest`` watches now, and hold them.

        For a consumer that cannot be sent to for a while (its stream or socket
        is full): a latest watch keeps, here, the newest change of each entry it
        was not sent (counting the ones it replaced in :attr:`Match.skipped`)
        instead of keeping its place in the history, so it never falls behind
        the history however long its consumer does not read; what is held is at
        most one change per entry. It stops, in a WM, at the first change a
        queue watch of the subscription still has to get, so that the stream
        keeps the host's order: a queue watch falls behind the history as
        before. The next polls deliver what is held, merged in the host's order.
        """
        by_sa = self._by_sa
        if by_sa is None:
            by_sa = self._by_sa = self._index()
        held = self._held
        for sa, watches in by_sa.items():
            latest = [w for w in watches if w.latest]
            if not latest:
                continue
            queue = [w for w in watches if not w.latest]
            start = min(w.next[sa] for w in watches)
            try:
                events = self._host.events_since(sa, start)
            except HistoryExpiredError:
                continue  # fell behind already: the next poll ends the stream with it
            last = start
            for ev in events:
                if any(ev.revision >= w.next[sa] and any(f.matches(ev) for f in w.filters) for w in queue):
                    break  # a queue watch's change: the stream delivers it first, in order
                last = ev.revision + 1
                ids, include = _matched(ev, sa, latest)
                if not ids:
                    continue
                match = Match(ev, ids, include)
                key = (sa, ev.id, tuple(ids))
                older = held.pop(key, None)
                if older is not None:
                    match.replaces(older)
                held[key] = match
            for w in watches:  # the queue watches too: none of them wanted a change before ``last``
                w.next[sa] = max(w.next[sa], last)

    def poll(self, max_events: int = 0, max_bytes: int = 0) -> list[Match]:
        """Pending events matching any watch, each once, in the host's order (per WM: by revision).

        ``max_events`` and ``max_bytes`` (entry bytes of matches that include
        their entry; 0: no cap) bound one batch; :attr:`behind` then tells that
        more is pending. HistoryExpiredError if a watch fell behind the history.
        """
        if self._held:
            return self._poll_held(max_events, max_bytes)
        return self._poll(max_events, max_bytes)

    def _poll_held(self, max_events: int, max_bytes: int) -> list[Match]:
        """:meth:`poll` with changes held for latest watches (:meth:`hold_latest`), merged in the host's order.

        A batch is everything merged when it keeps the bounds; else the held
        changes that come before every fresh one, as many as the bounds allow
        (at least one), or, when a fresh change comes first, that one alone:
        the fresh poll is then undone, so the stream never skips past a change.
        """
        self.hold_latest()  # newer changes of the latest watches replace what is held for their entries
        live = self._watches
        held: list[Match] = []
        for key, m in list(self._held.items()):
            m.watch_ids = [i for i in m.watch_ids if i in live]  # a watch cancelled since: not delivered
            if m.watch_ids:
                held.append(m)
            else:
                del self._held[key]
        held.sort(key=_seq)
        before = {w.watch_id: dict(w.next) for w in live.values()}
        fresh = self._poll(max_events, max_bytes)
        # A fresh poll cut short by its bounds leaves no room: then the branch below, never a held change
        # after the batch's last fresh one.
        out = list(heapq.merge(fresh, held, key=_seq))
        if not _within(out, max_events, max_bytes):
            for w in live.values():
                w.next = before[w.watch_id]
            first = fresh[0].event.seq if fresh else None
            out = []
            for m in held:
                if (first is not None and m.event.seq > first) or (out and not _within([*out, m], max_events,
                                                                                          max_bytes)):
                    break
                out.append(m)
            if not out:
                out = self._poll(1, 0)  # the first fresh change, which comes before every held one
            self.behind = True
        taken = {id(m) for m in out}
        for key, m in list(self._held.items()):
            if id(m) in taken:
                del self._held[key]
        counts: dict[str, int] = {}
        for m in out:
            counts[m.event.subarchitecture] = counts.get(m.event.subarchitecture, 0) + 1
        self.polled = list(counts.items())
        return out

    def _poll(self, max_events: int, max_bytes: int) -> list[Match]:
        self.behind = False
        by_sa = self._by_sa
        if by_sa is None:
            by_sa = self._by_sa = self._index()
        per_sa: list[list[Match]] = []
        polled: list[tuple[str, int]] = []
        self.polled = polled
        budget_events, budget_bytes = max_events, max_bytes
        exhausted = False
        for sa, watches in by_sa.items():
            if exhausted:
                self.behind = True  # conservative: a wake-up with nothing pending costs little
                break
            start = watches[0].next[sa] if len(watches) == 1 else min(w.next[sa] for w in watches)
            events = self._host.events_since(sa, start)
            if not events:
                continue
            matches: list[Match | None] = []
            latest = {w.watch_id for w in watches if w.latest}
            newest: dict[str, int] = {}  # entry id -> index in matches of its conflatable change
            conflated = False
            last = start
            for ev in events:
                last = ev.revision + 1
                ids, include = _matched(ev, sa, watches)
                if ids:
                    match = Match(ev, ids, include)
                    if latest and latest.issuperset(ids):
                        at = newest.get(ev.id)
                        older = matches[at] if at is not None else None
                        if older is not None and older.watch_ids == ids:
                            # The newer change replaces the older one, which gives back its budget.
                            match.replaces(older)
                            matches[at] = None  # type: ignore[index]
                            conflated = True
                            if max_events:
                                budget_events += 1
                            if max_bytes and older.include_entry and older.event.entry is not None:
                                budget_bytes += len(older.event.entry.data)
                        newest[ev.id] = len(matches)
                    matches.append(match)
                    if max_events:
                        budget_events -= 1
                    if max_bytes and include and ev.entry is not None:
                        budget_bytes -= len(ev.entry.data)
                    if (max_events and budget_events <= 0) or (max_bytes and budget_bytes <= 0):
                        exhausted = True
                        self.behind = last <= events[-1].revision
                        break
            for w in watches:
                w.next[sa] = max(w.next[sa], last)
            kept = [m for m in matches if m is not None] if conflated else matches
            if kept:
                per_sa.append(kept)  # type: ignore[arg-type]  # no None left once conflated ones are out
                polled.append((sa, len(kept)))
        if len(per_sa) == 1:
            return per_sa[0]
        return list(heapq.merge(*per_sa, key=lambda m: m.event.seq))

    def positions(self) -> dict[int, dict[str, int]]:
        """Next revision per SA of every watch (for resuming elsewhere)."""
        return {wid: dict(w.next) for wid, w in self._watches.items()}

    def _index(self) -> dict[str, list[_Watch]]:
        sas: set[str] = set()
        for w in self._watches.values():
            sas |= w.sas
        return {sa: [w for w in self._watches.values() if sa in w.sas] for sa in sorted(sas)}

    def close(self) -> None:
        """Stop being woken; drop every watch."""
        self._host.remove_listener(self._wake)
        self._watches.clear()
        self._by_sa = None
