"""Metrics in the core (cast.core.metrics): exact counts of known traffic through the rulebook, the
latency histogram, reports, merging servers, and counting off."""

from __future__ import annotations

import threading
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cast.core.access import Access, run_sync
from cast.core.metrics import BUCKETS_S, Metrics
from cast.core.metrics_view import COUNTERS, merge_snapshots, quantile
from cast.core.policies import make_policy
from cast.core.records import BatchOp, ChangeEvent, Identity, LockMode, Operation
from cast.core.reports import MAX_REPORT_NAMES
from cast.core.system import System
from cast.core.tasks import TaskOutcome
from cast.core.watch import EventFilter, Match, Subscription
from cast.errors import (
    AlreadyExistsError,
    DeadlineExceededError,
    InvalidArgumentError,
    LockedError,
    ResourceExhaustedError,
)
from tests.conftest import wait_for

WRITER = Identity("writer", "a", privileged=True)  # of SA a, writes into b
READER = Identity("reader", "b")
WATCHER = Identity("watcher", "c")
VALUE = b"0123456789"


def system(**options: Any) -> System:
    sys = System("m", ["a", "b", "c"], {"b": make_policy("fifo", {"max_concurrent": 1})}, **options)
    for who in (WRITER, READER, WATCHER):  # locks and tasks need a live session
        sys.sessions.register(who, "python", "managed", 1, "h")
    return sys


def zeros(**counts: Any) -> dict[str, Any]:
    """Every counter 0 but those given."""
    out: dict[str, Any] = dict.fromkeys(COUNTERS, 0)
    out.update(lock_wait_s=0.0, task_wait_s=0.0)
    out.update(counts)
    return out


def known_traffic(sys: System) -> None:
    """N=5 writes from a component of SA a into b's WM (3 adds, 1 overwrite, 1 delete), a batch of 2 more adds,
    M=4 reads by a component of b, one refused write, one lock wait, a task proposed, adopted and completed."""
    w, r, watcher = Access(sys, WRITER), Access(sys, READER), Access(sys, WATCHER)
    sub = Subscription(sys.host, lambda: None)
    watcher.watch(sub, 1, [EventFilter(subarchitecture="b", include_entry=True)])
    for i in range(3):
        run_sync(sys, w.write(BatchOp(Operation.ADD, "b", f"x{i}", "t.T", VALUE)))
    run_sync(sys, w.write(BatchOp(Operation.OVERWRITE, "b", "x0", "t.T", VALUE * 2)))
    run_sync(sys, w.write(BatchOp(Operation.DELETE, "b", "x2")))
    run_sync(sys, w.batch([BatchOp(Operation.ADD, "b", "y0", "t.T", VALUE), BatchOp(Operation.ADD, "b", "y1", "t.T")]))
    with pytest.raises(AlreadyExistsError):
        run_sync(sys, w.write(BatchOp(Operation.ADD, "b", "x1", "t.T", VALUE)))
    assert r.get("b", "x0").data == VALUE * 2
    assert r.get("b", "x1").data == VALUE
    assert len(r.get_by_type("b", "t.T")[0]) == 4  # x0, x1, y0, y1: 3 values of 10 or 20 bytes, one empty
    assert r.exists("b", "x9") is False
    # A lock wait: the reader waits for the writer's lock on x1.
    run_sync(sys, w.lock("b", "x1", LockMode.O))
    got: list[int] = []
    waiter = threading.Thread(target=lambda: got.append(run_sync(sys, r.lock("b", "x1", LockMode.O), timeout=20)))
    waiter.start()
    wait_for(lambda: sys.host._waiter_count == 1, what="the reader to wait")  # no public count of lock waiters
    run_sync(sys, w.unlock("b", "x1"))
    waiter.join(20)
    assert got == [1]
    run_sync(sys, r.unlock("b", "x1"))
    task = run_sync(sys, r.propose("look"))
    run_sync(sys, r.complete(task.task_id, TaskOutcome.SUCCEEDED))
    # Everything b's WM saw, handed to the watcher once (task entries included: 3 writes per task).
    matches = watcher.take(sub)
    assert [m.event.id for m in matches][:6] == ["x0", "x1", "x2", "x0", "x2", "y0"]
    sub.close()


def test_known_traffic_gives_exact_counts_per_component_wm_and_pair_of_sas() -> None:
    sys = system()
    known_traffic(sys)
    m = sys.metrics.snapshot()
    assert m["enabled"] and m["system"] == "m" and m["servers"] == 1
    comps = m["components"]
    writer, reader, watcher = comps["writer"], comps["reader"], comps["watcher"]
    assert writer == {"subarchitecture": "a", **zeros(writes=7, adds=5, overwrites=1, deletes=1, writes_refused=1,
                                                      bytes_in=60, locks=1)}
    assert reader["lock_wait_s"] > 0 and reader["task_wait_s"] >= 0  # times: measured, not asserted
    assert reader == {"subarchitecture": "b", **zeros(reads=4, entries_read=6, bytes_out=70, locks=1, lock_waits=1,
                                                      tasks_proposed=1, tasks_adopted=1, tasks_completed=1,
                                                      lock_wait_s=reader["lock_wait_s"],
                                                      task_wait_s=reader["task_wait_s"])}
    # The watcher got the 7 writes and the task's 4 (add, overwrite when adopted, overwrite and delete when
    # completed), each with its value: x0, x1, x2 (10 each), x0 (20), the deleted x2 (10), y0 (10), y1 (0),
    # and the task entries.
    task_bytes = sum(len(ev.entry.data) for ev in sys.host.events_since("b", 8) if ev.entry is not None)
    assert watcher == {"subarchitecture": "c", **zeros(events=11, event_bytes=70 + task_bytes,
                                                       bytes_out=70 + task_bytes)}
    b = m["subarchitectures"]["b"]
    assert b["task_wait"]["count"] == 1
    b = {k: v for k, v in b.items() if k not in ("task_wait", "lock_wait_s", "task_wait_s")}
    assert b == {k: v for k, v in zeros(reads=4, entries_read=6, writes=7, adds=5, overwrites=1, deletes=1,
                                        bytes_in=60, bytes_out=70 + 70 + task_bytes, events=11,
                                        event_bytes=70 + task_bytes, locks=2, lock_waits=1, tasks_proposed=1,
                                        tasks_adopted=1, tasks_completed=1).items()
                 if k not in ("writes_refused", "lock_wait_s", "task_wait_s")}
    assert m["subarchitectures"]["a"]["writes"] == 0 and m["subarchitectures"]["c"]["reads"] == 0
    assert m["traffic"] == [
        {"from_sa": "a", "to_sa": "b", "reads": 0, "writes": 7, "bytes_in": 60, "bytes_out": 0, "events": 0},
        {"from_sa": "b", "to_sa": "b", "reads": 4, "writes": 0, "bytes_in": 0, "bytes_out": 70, "events": 0},
        {"from_sa": "c", "to_sa": "b", "reads": 0, "writes": 0, "bytes_in": 0, "bytes_out": 70 + task_bytes,
         "events": 11},
    ]
    latency = m["delivery_latency"]
    assert list(latency["watchers"]) == ["watcher"] and latency["watchers"]["watcher"]["subarchitecture"] == "c"
    assert latency["watchers"]["watcher"]["count"] == latency["all"]["count"] == 11
    assert sum(latency["all"]["buckets"]) == 11 and len(latency["all"]["buckets"]) == len(BUCKETS_S) + 1


def test_an_event_under_another_components_odr_lock_is_counted_without_its_value() -> None:
    sys = system()
    w, watcher = Access(sys, WRITER), Access(sys, WATCHER)
    run_sync(sys, w.write(BatchOp(Operation.ADD, "b", "x", "t.T", VALUE)))
    run_sync(sys, w.lock("b", "x", LockMode.ODR))
    sub = Subscription(sys.host, lambda: None)
    watcher.watch(sub, 1, [EventFilter(subarchitecture="b", include_entry=True)])
    run_sync(sys, w.write(BatchOp(Operation.OVERWRITE, "b", "x", "t.T", VALUE)))
    assert len(watcher.take(sub)) == 1
    c = sys.metrics.snapshot()["components"]["watcher"]
    assert (c["events"], c["event_bytes"], c["bytes_out"]) == (1, 0, 0)  # the event went without the value


def test_a_lock_wait_that_times_out_is_counted_and_a_no_wait_refusal_is_not() -> None:
    sys = system()
    w, r = Access(sys, WRITER), Access(sys, READER)
    run_sync(sys, w.write(BatchOp(Operation.ADD, "b", "x", "t.T", VALUE)))
    run_sync(sys, w.lock("b", "x", LockMode.O))
    with pytest.raises(DeadlineExceededError):
        run_sync(sys, r.lock("b", "x", LockMode.O), timeout=0.05)
    with pytest.raises(LockedError):
        run_sync(sys, r.lock("b", "x", LockMode.O, no_wait=True))
    c = sys.metrics.snapshot()["components"]["reader"]
    assert (c["lock_waits"], c["locks"]) == (1, 0)
    assert c["lock_wait_s"] > 0


def test_counting_off_counts_nothing_but_keeps_reports() -> None:
    sys = system(metrics=False)
    known_traffic(sys)
    sys.metrics.report("reader", "score", 2)
    m = sys.metrics.snapshot()
    assert m["enabled"] is False
    assert m["components"] == {} and m["traffic"] == [] and m["delivery_latency"]["watchers"] == {}
    assert all(counts["writes"] == 0 and counts["tasks_proposed"] == 0 for counts in m["subarchitectures"].values())
    assert m["reports"]["reader"]["score"]["count"] == 1


def test_reports_aggregate_per_component_and_name_and_bad_ones_are_refused() -> None:
    metrics = Metrics("m", ["a"])
    for value in (3, -1.5, 7):
        metrics.report("c1", "answers_correct", value)
    metrics.report("c2", "answers_correct", 1)
    r = metrics.snapshot()["reports"]
    got = {k: v for k, v in r["c1"]["answers_correct"].items() if k != "last_time"}
    assert got == {"count": 3, "sum": 8.5, "min": -1.5, "max": 7.0, "last": 7.0, "mean": 8.5 / 3}
    assert r["c2"]["answers_correct"]["count"] == 1
    for name, value in (("", 1), ("x" * 129, 1), ("n", float("nan")), ("n", float("inf"))):
        with pytest.raises(InvalidArgumentError):
            metrics.report("c1", name, value)
    for i in range(MAX_REPORT_NAMES - 1):
        metrics.report("c1", f"m{i}", i)
    with pytest.raises(ResourceExhaustedError, match="limit"):
        metrics.report("c1", "one-too-many", 1)
    metrics.report("c1", "answers_correct", 1)  # a known name is still taken


@pytest.mark.incompatible_with_mypyc  # compiled, the annotation refuses it first, with a TypeError
def test_a_report_value_that_is_not_a_number_is_refused_by_name() -> None:
    with pytest.raises(InvalidArgumentError, match="report 'n': the value must be a number, got 'many'"):
        Metrics("m", ["a"]).report("c1", "n", "many")  # type: ignore[arg-type]


def _match(sa: str, time_ns: int) -> Match:
    ev = ChangeEvent(1, 1, Operation.ADD, sa, "x", "t.T", "w", "a", 0, time_ns, None, None)
    return Match(ev, [1], False)


def _delivered(metrics: Metrics, ages_ns: list[int], now: int) -> dict[str, Any]:
    """Hand events of the given ages to one watcher at ``now``; its histogram."""
    polled = Subscription(System("m", ["a"]).host, lambda: None)
    polled.polled = [("a", len(ages_ns))]  # what a Subscription polled
    metrics.delivered(Identity("watcher", "a"), polled, [_match("a", now - a) for a in ages_ns],
                      lambda m: False)
    latency: dict[str, Any] = metrics.snapshot()["delivery_latency"]["watchers"]["watcher"]
    return latency


@pytest.mark.parametrize("one_by_one", [False, True], ids=["batch", "single"])
def test_latency_is_from_the_events_commit_time_into_its_bucket(one_by_one: bool) -> None:
    now = 10_000_000_000
    metrics = Metrics("m", ["a"], clock=lambda: now)
    # 40 µs, exactly 1 ms (a bound is in its own bucket), 7 s, 400 s (above the last bound), a clock step back.
    ages_ns = [40_000, 1_000_000, 7_000_000_000, 400_000_000_000, -5]
    for batch in ([a] for a in ages_ns) if one_by_one else [ages_ns]:
        hist = _delivered(metrics, batch, now)
    buckets = hist["buckets"]
    assert buckets[0] == 2  # 40 µs and the negative one, counted as 0
    assert buckets[BUCKETS_S.index(0.001)] == 1
    assert buckets[BUCKETS_S.index(10.0)] == 1
    assert buckets[-1] == 1 and sum(buckets) == 5
    assert hist["sum_s"] == pytest.approx((40_000 + 1_000_000 + 7_000_000_000 + 400_000_000_000) / 1e9)


@given(st.lists(st.integers(min_value=0, max_value=400_000_000_000), min_size=2, max_size=60))
def test_a_batch_counts_as_its_events_one_by_one(ages_ns: list[int]) -> None:
    now = 500_000_000_000
    batched, single = Metrics("m", ["a"], clock=lambda: now), Metrics("m", ["a"], clock=lambda: now)
    got = _delivered(batched, ages_ns, now)
    for age in ages_ns:
        want = _delivered(single, [age], now)
    assert (got["buckets"], got["count"]) == (want["buckets"], len(ages_ns))
    assert got["sum_s"] == pytest.approx(want["sum_s"])


def test_quantiles_are_estimated_within_their_bucket() -> None:
    bounds = (1.0, 2.0, 4.0)
    assert quantile([0, 0, 0, 0], bounds, 0.5) == 0.0
    assert quantile([10, 0, 0, 0], bounds, 0.5) == 0.5
    assert quantile([0, 10, 0, 0], bounds, 0.5) == 1.5
    assert quantile([5, 0, 5, 0], bounds, 0.99) == pytest.approx(2 + 2 * 4.9 / 5)
    assert quantile([0, 0, 0, 3], bounds, 0.5) == 4.0  # above the last bound: that bound


def test_servers_merge_into_one_systems_metrics() -> None:
    one, two = system(), System("m", ["d"])
    known_traffic(one)
    w = Access(two, WRITER)
    run_sync(two, w.write(BatchOp(Operation.ADD, "d", "z", "t.T", VALUE)))
    one.metrics.report("reader", "score", 1)
    two.metrics.report("reader", "score", 5)
    merged = merge_snapshots([one.metrics.snapshot(), two.metrics.snapshot()])
    assert merged["servers"] == 2
    assert merged["components"]["writer"]["writes"] == 8 and merged["components"]["writer"]["bytes_in"] == 70
    assert sorted(merged["subarchitectures"]) == ["a", "b", "c", "d"]
    assert [(c["from_sa"], c["to_sa"], c["writes"]) for c in merged["traffic"] if c["writes"]] == [
        ("a", "b", 7), ("a", "d", 1)]
    score = merged["reports"]["reader"]["score"]
    assert (score["count"], score["sum"], score["min"], score["max"], score["last"]) == (2, 6.0, 1.0, 5.0, 5.0)
    assert merged["delivery_latency"]["all"]["count"] == 11
    alone = one.metrics.snapshot()
    assert merge_snapshots([alone]) == alone
