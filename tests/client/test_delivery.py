"""Delivery policies (queue, latest) and receiver priorities of on_change."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from cast_testing_pb2 import Pose

import cast
from cast.core.records import BatchOp, Identity, Operation
from cast.core.system import System
from cast.core.watch import EventFilter, Subscription
from cast.server.wire import wire_system
from tests.conftest import wait_for


class Slow(cast.UnmanagedComponent):
    """Records (x, skipped) of each change it is given, sleeping in each callback like a slow consumer."""

    def __init__(self) -> None:
        self.seen: list[tuple[float, int]] = []
        self.pause = 0.2

    def record(self, change: cast.WorkingMemoryChange) -> None:
        self.seen.append((change.entry(Pose).value.x, change.skipped))
        time.sleep(self.pause)


def test_latest_gives_a_slow_callback_the_newest_value_and_counts_what_it_skipped(make_component: Any) -> None:
    reader = make_component(Slow, "reader")
    writer = make_component(cast.UnmanagedComponent, "writer")
    reader.on_change(cast.ChangeFilter(id="img", include_entry=True), reader.record, delivery="latest")
    writer.add("img", Pose(x=0))
    for i in range(1, 51):
        writer.overwrite("img", Pose(x=i))
    calls_when_writer_stopped = len(reader.seen)
    wait_for(lambda: reader.seen and reader.seen[-1][0] == 50, what="the newest value")
    # The callback running when the writer stopped, then the newest: nothing older in between.
    assert len(reader.seen) <= calls_when_writer_stopped + 2, reader.seen
    assert len(reader.seen) < 51
    assert sum(skipped for _, skipped in reader.seen) + len(reader.seen) == 51  # every change counted once
    assert [x for x, _ in reader.seen] == sorted(x for x, _ in reader.seen)


def test_queue_delivers_every_change_in_order(make_component: Any) -> None:
    reader = make_component(Slow, "reader")
    reader.pause = 0.001
    writer = make_component(cast.UnmanagedComponent, "writer")
    reader.on_change(cast.ChangeFilter(id="img", include_entry=True), reader.record)
    writer.add("img", Pose(x=0))
    for i in range(1, 51):
        writer.overwrite("img", Pose(x=i))
    wait_for(lambda: len(reader.seen) == 51, what="all 51 changes")
    assert reader.seen == [(float(i), 0) for i in range(51)]


def test_high_priority_callbacks_run_before_pending_low_ones(make_component: Any) -> None:
    reader = make_component(cast.UnmanagedComponent, "reader")
    writer = make_component(cast.UnmanagedComponent, "writer")
    gate = threading.Event()
    blocking = threading.Event()
    order: list[str] = []

    def block(change: cast.WorkingMemoryChange) -> None:
        blocking.set()
        gate.wait(30)

    reader.on_change(cast.ChangeFilter(id="block"), block)
    reader.on_change(cast.ChangeFilter(id="low"), lambda ch: order.append("low"), priority="low")
    reader.on_change(cast.ChangeFilter(id="mid"), lambda ch: order.append("mid"))
    reader.on_change(cast.ChangeFilter(id="high"), lambda ch: order.append("high"), priority=cast.Priority.HIGH)
    writer.add("block", Pose())
    # Running before the rest arrive: a dispatcher slow to wake would otherwise find "high" queued
    # too, run it first (as it should), and the six would never be pending at once.
    wait_for(blocking.is_set, what="the blocking callback to start")
    writer.add("low", Pose())
    writer.overwrite("low", Pose())
    writer.add("mid", Pose())
    writer.add("high", Pose())
    writer.overwrite("low", Pose())
    writer.overwrite("high", Pose())
    # the blocking callback (still counted while it runs) and the six behind it
    wait_for(lambda: reader._dispatcher.room() <= reader.max_pending_callbacks - 7, what="six callbacks pending")
    gate.set()
    wait_for(lambda: len(order) == 6, what="the six callbacks")
    assert order == ["high", "high", "mid", "low", "low", "low"]


def test_bad_delivery_or_priority_is_refused_naming_the_choices(make_component: Any) -> None:
    reader = make_component(cast.UnmanagedComponent, "reader")
    with pytest.raises(cast.InvalidArgumentError, match="'queue' or 'latest'"):
        reader.on_change(cast.ChangeFilter(), lambda ch: None, delivery="newest")
    with pytest.raises(cast.InvalidArgumentError, match="'high', 'medium' or 'low'"):
        reader.on_change(cast.ChangeFilter(), lambda ch: None, priority="urgent")


def test_the_server_conflates_a_latest_watchers_backlog_to_one_change_per_entry() -> None:
    system: System = wire_system("t", ["vision"])
    who = Identity("w", "vision")
    sub = Subscription(system.host, lambda: None)
    sub.add_watch(1, [EventFilter(id="img", include_entry=True)], latest=True)
    sub.add_watch(2, [EventFilter(id="log")])  # a queue watch on the same stream keeps every change
    system.host.write(who, BatchOp(Operation.ADD, "vision", "img", "t.P", b"0"))
    system.host.write(who, BatchOp(Operation.ADD, "vision", "log", "t.P", b"0"))
    for i in range(1, 1000):
        system.host.write(who, BatchOp(Operation.OVERWRITE, "vision", "img", "t.P", str(i).encode()))
        if i % 100 == 0:
            system.host.write(who, BatchOp(Operation.OVERWRITE, "vision", "log", "t.P", str(i).encode()))
    # Budgets as the server's (4 MiB, 4096 events): conflated ones give theirs back, so one poll reaches the newest.
    matches = sub.poll(4096, 4 * 1024 * 1024)
    images = [m for m in matches if m.event.id == "img"]
    logs = [m for m in matches if m.event.id == "log"]
    assert len(images) == 1 and images[0].event.entry is not None and images[0].event.entry.data == b"999"
    assert images[0].skipped == 999 and images[0].first_skipped == 1
    assert len(logs) == 10 and all(m.skipped == 0 for m in logs)
    assert not sub.behind
