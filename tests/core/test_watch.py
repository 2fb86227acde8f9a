"""Watch cursors: filters, exactly-once delivery in order, resume, history overflow."""

from __future__ import annotations

import pytest

from cast.core.host import MemoryHost
from cast.core.records import Identity, Limits, Operation
from cast.core.watch import EventFilter, Subscription
from cast.errors import HistoryExpiredError, InvalidArgumentError, NotFoundError, ResourceExhaustedError

V = Identity("v", "vision")
L = Identity("l", "language")


def make(limits: Limits | None = None) -> tuple[MemoryHost, Subscription, list[int]]:
    host = MemoryHost(["vision", "language"], limits)
    wakes: list[int] = []
    return host, Subscription(host, lambda: wakes.append(1)), wakes


def test_several_filters_and_watches_each_event_once_with_matching_ids() -> None:
    host, sub, wakes = make()
    sub.add_watch(1, [EventFilter(type="t.A"), EventFilter(operations=frozenset({Operation.DELETE}))])
    sub.add_watch(2, [EventFilter(subarchitecture="language")])
    sub.add_watch(3, [EventFilter(source_component="v", id="x")])
    host.add(V, "vision", "x", "t.A", b"")
    host.add(V, "vision", "y", "t.B", b"")
    host.add(L, "language", "z", "t.B", b"")
    host.delete(V, "vision", "y")
    assert wakes  # writers wake the subscription
    got = [(m.event.subarchitecture, m.event.id, m.event.operation, m.watch_ids) for m in sub.poll()]
    assert got == [
        ("vision", "x", Operation.ADD, [1, 3]),
        ("language", "z", Operation.ADD, [2]),
        ("vision", "y", Operation.DELETE, [1]),
    ]
    assert sub.poll() == []  # nothing twice


def test_events_come_in_host_order_across_wms_and_revision_order_within() -> None:
    host, sub, _ = make()
    sub.add_watch(1, [EventFilter()])
    for i in range(20):
        who, sa = (V, "vision") if i % 3 else (L, "language")
        host.add(who, sa, f"e{i}", "t.T", b"")
    matches = sub.poll()
    assert [m.event.id for m in matches] == [f"e{i}" for i in range(20)]
    for sa in ("vision", "language"):
        revs = [m.event.revision for m in matches if m.event.subarchitecture == sa]
        assert revs == list(range(1, len(revs) + 1))


def test_a_new_watch_sees_only_later_changes_unless_it_resumes() -> None:
    host, sub, _ = make()
    host.add(V, "vision", "old", "t.T", b"")
    revisions = sub.add_watch(1, [EventFilter()])
    assert revisions == {"vision": 1, "language": 0}
    host.add(V, "vision", "new", "t.T", b"")
    assert [m.event.id for m in sub.poll()] == ["new"]
    sub.add_watch(2, [EventFilter(subarchitecture="vision")], {"vision": 1})
    replay = sub.poll()
    assert [(m.event.id, m.watch_ids) for m in replay] == [("old", [2]), ("new", [2])]


def test_watches_added_and_cancelled_between_polls_take_effect_at_the_next_poll() -> None:
    # poll keeps an index of the watches per WM; adding or cancelling one must refresh it.
    host, sub, _ = make()
    sub.add_watch(1, [EventFilter(subarchitecture="vision")])
    host.add(V, "vision", "a", "t.T", b"")
    assert [(m.event.id, m.watch_ids) for m in sub.poll()] == [("a", [1])]
    sub.add_watch(2, [EventFilter(subarchitecture="language")])  # a WM no watch covered before
    sub.add_watch(3, [EventFilter(subarchitecture="vision")])
    host.add(L, "language", "b", "t.T", b"")
    host.add(V, "vision", "c", "t.T", b"")
    assert [(m.event.id, m.watch_ids) for m in sub.poll()] == [("b", [2]), ("c", [1, 3])]
    assert sub.cancel(1) and sub.cancel(2)
    host.add(L, "language", "d", "t.T", b"")
    host.add(V, "vision", "e", "t.T", b"")
    assert [(m.event.id, m.watch_ids) for m in sub.poll()] == [("e", [3])]
    assert sub.cancel(3)
    host.add(V, "vision", "f", "t.T", b"")
    assert sub.poll() == []


def test_resume_older_than_history_is_refused_with_resync_advice() -> None:
    host, sub, _ = make(Limits(history_events=4))
    for i in range(10):
        host.add(V, "vision", f"e{i}", "t.T", b"")
    assert host.history_bounds("vision") == (7, 10)
    with pytest.raises(HistoryExpiredError, match="revision 3 is no longer in the history.*kept: 7..10.*resynchronise"):
        sub.add_watch(1, [EventFilter()], {"vision": 3})
    sub.add_watch(1, [EventFilter()], {"vision": 7})
    assert [m.event.revision for m in sub.poll()] == [7, 8, 9, 10]


def test_a_watcher_that_falls_behind_is_told_never_silently_skipped() -> None:
    host, sub, _ = make(Limits(history_events=8))
    sub.add_watch(1, [EventFilter()])
    for i in range(5):
        host.add(V, "vision", f"e{i}", "t.T", b"")
    assert len(sub.poll()) == 5
    for i in range(5, 30):  # writers are never blocked by the slow watcher
        host.add(V, "vision", f"e{i}", "t.T", b"")
    with pytest.raises(HistoryExpiredError):
        sub.poll()


def test_history_is_bounded_by_bytes_too() -> None:
    host, _, _ = make(Limits(history_events=1000, history_bytes=100))
    for i in range(10):
        host.add(V, "vision", f"e{i}", "t.T", b"x" * 30)
    first, last = host.history_bounds("vision")
    assert last == 10 and last - first + 1 <= 4


def test_poll_budget_splits_batches_without_loss() -> None:
    host, sub, _ = make()
    sub.add_watch(1, [EventFilter(include_entry=True)])
    for i in range(10):
        host.add(V, "vision", f"e{i}", "t.T", b"")
    seen = []
    while True:
        batch = sub.poll(max_events=3)
        seen.extend(m.event.revision for m in batch)
        if not sub.behind:
            break
    assert seen == list(range(1, 11))


def test_bad_watches_are_refused() -> None:
    _, sub, _ = make()
    with pytest.raises(InvalidArgumentError, match="at least one filter"):
        sub.add_watch(1, [])
    with pytest.raises(NotFoundError, match="no subarchitecture 'motor'"):
        sub.add_watch(1, [EventFilter(subarchitecture="motor")])
    with pytest.raises(InvalidArgumentError, match="in the future"):
        sub.add_watch(1, [EventFilter()], {"vision": 5})
    sub.add_watch(1, [EventFilter()])
    with pytest.raises(InvalidArgumentError, match="already in use"):
        sub.add_watch(1, [EventFilter()])
    assert sub.cancel(1) and not sub.cancel(1)


def test_watcher_limit() -> None:
    host = MemoryHost(["vision"], Limits(max_watchers=1))
    first = Subscription(host, lambda: None)
    with pytest.raises(ResourceExhaustedError, match="max_watchers = 1"):
        Subscription(host, lambda: None)
    first.close()
    Subscription(host, lambda: None)


def test_any_matching_filter_that_asks_for_the_entry_gets_it() -> None:
    host, sub, _ = make()
    # The first filter matches without the entry; a later one that matches too asks for it.
    sub.add_watch(1, [EventFilter(subarchitecture="vision"), EventFilter(type="t.A", include_entry=True)])
    host.add(V, "vision", "x", "t.A", b"a")
    host.add(V, "vision", "y", "t.B", b"b")
    got = [(m.event.id, m.include_entry) for m in sub.poll()]
    assert got == [("x", True), ("y", False)]


# A latest watch whose consumer cannot be sent to: the server holds the newest change per entry for it
# (Subscription.hold_latest, called while the stream or socket is full), so it never falls behind the history.


def _images(host: MemoryHost, ids: list[str], rounds: int, sub: Subscription | None = None) -> int:
    """Overwrite each entry of ``ids`` ``rounds`` times, the subscription held after every write; the writes."""
    writes = 0
    for r in range(rounds):
        for entry in ids:
            host.overwrite(V, "vision", entry, "t.T", f"{entry}-{r}".encode())
            writes += 1
            if sub is not None:
                sub.hold_latest()
    return writes


def test_a_held_latest_watch_never_falls_behind_the_history_and_counts_every_change_it_skipped() -> None:
    host, sub, _ = make(Limits(history_events=10))
    stalled = Subscription(host, lambda: None)  # the same watch never held: it falls behind, as a queue one
    for s in (sub, stalled):
        s.add_watch(1, [EventFilter(subarchitecture="vision", include_entry=True)], latest=True)
    ids = ["a", "b", "c"]
    for entry in ids:
        host.add(V, "vision", entry, "t.T", b"")
    sub.hold_latest()
    writes = 3 + _images(host, ids, 200, sub)
    matches = sub.poll(4096, 4 << 20)
    assert [m.event.id for m in matches] == ids  # one per entry, in the host's order of their newest change
    assert [m.event.entry.data for m in matches if m.event.entry] == [f"{e}-199".encode() for e in ids]
    assert sum(1 + m.skipped for m in matches) == writes
    assert [m.first_skipped for m in matches] == [1, 2, 3]  # the adds
    assert sub.poll() == [] and not sub.behind
    with pytest.raises(HistoryExpiredError):
        stalled.poll()


def test_held_changes_keep_the_host_order_with_a_queue_watch_of_the_same_stream() -> None:
    host, sub, _ = make(Limits(history_events=10))
    sub.add_watch(1, [EventFilter(id="img")], latest=True)
    sub.add_watch(2, [EventFilter(id="cmd")])  # a queue watch: every change, in order
    host.add(V, "vision", "img", "t.T", b"")
    host.add(V, "vision", "cmd", "t.T", b"")
    sub.hold_latest()  # stops at the add of cmd, which the queue watch has not had
    _images(host, ["img"], 3, sub)
    host.overwrite(V, "vision", "cmd", "t.T", b"go")
    _images(host, ["img"], 2, sub)
    got = [(m.event.id, m.event.revision, m.watch_ids, m.skipped) for m in sub.poll()]
    # img's first change was held before cmd's add; the rest came after it and conflate in the poll.
    assert got == [("img", 1, [1], 0), ("cmd", 2, [2], 0), ("cmd", 6, [2], 0), ("img", 8, [1], 4)]
    # While the queue watch's change is pending, the latest watch holds nothing past it: the queue watch
    # falls behind the history, and the stream with it, as before.
    host.overwrite(V, "vision", "cmd", "t.T", b"stop")
    _images(host, ["img"], 10, sub)
    with pytest.raises(HistoryExpiredError):
        sub.poll()


def test_held_changes_are_delivered_within_the_batch_bounds_in_order_and_once() -> None:
    host, sub, _ = make(Limits(history_events=5))
    sub.add_watch(1, [EventFilter(id="q")])
    sub.add_watch(2, [EventFilter(type="t.I")], latest=True)
    names = [f"i{i}" for i in range(8)]
    for entry in names:
        host.add(V, "vision", entry, "t.I", b"")
        sub.hold_latest()
    host.add(V, "vision", "q", "t.Q", b"")
    got: list[tuple[str, int]] = []
    for _ in range(10):
        batch = sub.poll(max_events=3)
        assert len(batch) <= 3
        got += [(m.event.id, m.event.revision) for m in batch]
        if not sub.behind:
            break
    assert got == [(name, i + 1) for i, name in enumerate(names)] + [("q", 9)]
    assert sub.poll() == []


def test_a_cancelled_watchs_held_changes_are_dropped() -> None:
    host, sub, _ = make(Limits(history_events=4))
    sub.add_watch(1, [EventFilter(id="a")], latest=True)
    sub.add_watch(2, [EventFilter(id="b")], latest=True)
    host.add(V, "vision", "a", "t.T", b"")
    host.add(V, "vision", "b", "t.T", b"")
    sub.hold_latest()
    assert sub.cancel(1)
    assert [(m.event.id, m.watch_ids) for m in sub.poll()] == [("b", [2])]


@pytest.mark.parametrize("seed", range(20))
def test_held_and_polled_changes_together_keep_every_rule_of_a_stream(seed: int) -> None:
    """Random writes, holds and batch bounds: every queue watch gets each of its changes once in order, every latest
    watch each entry's newest with every other counted as skipped, and the stream stays in the host's order."""
    import random

    rnd = random.Random(seed)
    host, sub, _ = make(Limits(history_events=100_000))
    entries = ["a", "b", "c", "d"]
    watches = {1: (EventFilter(subarchitecture="vision", id="a"), False),
               2: (EventFilter(subarchitecture="vision"), True),
               3: (EventFilter(subarchitecture="vision", id="b"), True),
               4: (EventFilter(type="t.Q"), False)}
    for wid, (f, latest) in watches.items():
        sub.add_watch(wid, [f], latest=latest)
    for e in entries:
        host.add(V, "vision", e, "t.Q" if e == "d" else "t.T", b"")
    host.add(L, "language", "q", "t.Q", b"")
    got: dict[int, list[tuple[str, int, int]]] = {wid: [] for wid in watches}  # entry, revision, skipped
    order: list[tuple[str, int]] = []
    for step in range(400):
        r = rnd.random()
        if r < 0.6:
            e = rnd.choice(entries)
            host.overwrite(V, "vision", e, "t.Q" if e == "d" else "t.T", str(step).encode())
            if rnd.random() < 0.1:
                host.overwrite(L, "language", "q", "t.Q", b"")
        elif r < 0.8:
            sub.hold_latest()
        else:
            for m in sub.poll(max_events=rnd.choice([0, 1, 2, 5])):
                order.append((m.event.subarchitecture, m.event.revision))
                for wid in m.watch_ids:
                    got[wid].append((m.event.id, m.event.revision, m.skipped))
    while True:
        batch = sub.poll()
        for m in batch:
            order.append((m.event.subarchitecture, m.event.revision))
            for wid in m.watch_ids:
                got[wid].append((m.event.id, m.event.revision, m.skipped))
        if not batch:
            break
    for sa in ("vision", "language"):
        revisions = [r for s, r in order if s == sa]
        assert revisions == sorted(set(revisions)), f"{sa}: out of order or twice"
    changes = {sa: host.events_since(sa, 1) for sa in ("vision", "language")}
    everything = [ev for sa in changes for ev in changes[sa]]
    for wid, (f, latest) in watches.items():
        mine = [ev for ev in everything if f.matches(ev)]  # the watches began before the adds
        if not latest:  # every change once, in order per WM (the host's order across WMs within a batch)
            assert sorted((e, r) for e, r, _ in got[wid]) == sorted((ev.id, ev.revision) for ev in mine), wid
            for sa in ("vision", "language"):
                ids = {ev.id for ev in mine if ev.subarchitecture == sa}
                revisions = [r for e, r, _ in got[wid] if e in ids]
                assert revisions == sorted(revisions), (wid, sa)
            assert all(s == 0 for _, _, s in got[wid])
        else:
            for entry in {ev.id for ev in mine}:
                of_entry = [g for g in got[wid] if g[0] == entry]
                assert sum(1 + s for _, _, s in of_entry) == sum(1 for ev in mine if ev.id == entry), (wid, entry)
                assert of_entry[-1][1] == max(ev.revision for ev in mine if ev.id == entry), (wid, entry)
