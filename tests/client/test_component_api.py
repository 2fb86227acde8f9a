"""The Python component API, each test run against a remote server and in process."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from cast_testing_pb2 import Counter, Pose

import cast
from cast.core.records import Identity, Operation
from tests.conftest import wait_for


def test_write_read_and_versions(make_component: Any) -> None:
    c = make_component(cast.UnmanagedComponent, "c")
    # A new journal starts versions at 0; a memory-only server at its epoch floor (cast.core.versions).
    v0 = make_component.system.host.version_floor
    assert (v0 == 0) == make_component.mode.endswith("-journal")
    entry_id = c.new_id()
    assert c.add(entry_id, Pose(x=1, label="cup")) == cast.WriteResult(1, v0)
    assert c.exists(entry_id)
    assert c.overwrite(entry_id, Pose(x=2, label="cup")).version == v0 + 1
    entry = c.get_entry(entry_id, Pose)
    assert (entry.value.x, entry.version, entry.author, entry.address) == (2, v0 + 1, "c", (entry_id, "vision"))
    with pytest.raises(cast.ConsistencyError, match=f"at version {v0 + 1}, expected {v0}"):
        c.overwrite(entry_id, Pose(), expected_version=v0)
    with pytest.raises(cast.AlreadyExistsError):
        c.add(entry_id, Pose())
    assert c.delete_entry(entry_id, expected_version=v0 + 1).version == v0 + 1
    assert not c.exists(entry_id)
    with pytest.raises(cast.NotFoundError):
        c.get(entry_id, Pose)
    assert c.add(entry_id, Pose()).version == v0 + 2  # re-add continues


def test_new_ids_are_unique(make_component: Any) -> None:
    a = make_component(cast.UnmanagedComponent, "a")
    b = make_component(cast.UnmanagedComponent, "b")
    ids = {a.new_id() for _ in range(500)} | {b.new_id() for _ in range(500)}
    assert len(ids) == 1000


def test_reads_and_writes_are_copies(make_component: Any) -> None:
    c = make_component(cast.UnmanagedComponent, "c")
    value = Pose(label="before", tags=["a"])
    c.add("x", value)
    value.label = "changed after add"
    value.tags.append("b")
    first = c.get("x", Pose)
    assert first.label == "before" and list(first.tags) == ["a"]
    first.label = "changed after get"
    assert c.get("x", Pose).label == "before"
    assert c.get_all(Pose)[0].value is not c.get_all(Pose)[0].value


def test_get_with_the_wrong_class_names_both_types(make_component: Any) -> None:
    c = make_component(cast.UnmanagedComponent, "c")
    c.add("x", Pose())
    with pytest.raises(cast.InvalidArgumentError, match="has type cast.testing.Pose, not cast.testing.Counter"):
        c.get("x", Counter)


def test_get_all_newest_first_with_limit_and_other_sa(make_component: Any) -> None:
    c = make_component(cast.UnmanagedComponent, "c")
    other = make_component(cast.UnmanagedComponent, "l", "language")
    for i in range(4):
        c.add(f"p{i}", Pose(x=i))
    c.add("n", Counter())
    assert [e.id for e in c.get_all(Pose)] == ["p3", "p2", "p1", "p0"]
    assert [e.value.x for e in other.get_all(Pose, subarchitecture="vision", limit=2)] == [3, 2]
    assert other.get_all(Pose) == []


def test_unprivileged_cross_sa_write_is_refused(make_component: Any) -> None:
    lang = make_component(cast.UnmanagedComponent, "parser", "language")
    boss = make_component(cast.UnmanagedComponent, "boss", "language", privileged=True)
    with pytest.raises(cast.PermissionDeniedError, match="component 'parser' \\(SA 'language'\\).*'vision'"):
        lang.add("goal", Pose(), subarchitecture="vision")
    boss.add("goal", Pose(label="go"), subarchitecture="vision")
    assert lang.get("goal", Pose, subarchitecture="vision").label == "go"


def test_batch(make_component: Any) -> None:
    c = make_component(cast.UnmanagedComponent, "c")
    results = c.batch(
        [("add", "a", Pose()), ("add", "b", Pose()), ("overwrite", "a", Pose(x=1)), ("delete", "b", None)]
    )
    v0 = make_component.system.host.version_floor
    assert [r.version - v0 for r in results] == [0, 0, 1, 0]
    with pytest.raises(cast.AlreadyExistsError, match="batch operation 1"):
        c.batch([("add", "c", Pose()), ("add", "a", Pose())])
    assert not c.exists("c")


def test_callbacks_run_on_one_dispatcher_thread_in_revision_order(make_component: Any) -> None:
    watcher = make_component(cast.UnmanagedComponent, "w", "language")
    writer = make_component(cast.UnmanagedComponent, "c")
    seen: list[tuple[int, str]] = []
    threads: set[int] = set()

    def record(change: cast.WorkingMemoryChange) -> None:
        threads.add(threading.get_ident())
        seen.append((change.revision, change.id))

    watcher.on_change(cast.global_type_filter(Pose), record)
    watcher.on_change(cast.operation_filter(Operation.DELETE), record)
    for i in range(50):
        writer.add(f"e{i}", Pose(x=i))
    writer.delete_entry("e0")
    wait_for(lambda: len(seen) >= 52)
    assert [r for r, _ in seen] == list(range(1, 51)) + [51, 51]  # the delete matched both
    assert len(threads) == 1 and threading.get_ident() not in threads


def test_filter_helpers(make_component: Any) -> None:
    me = make_component(cast.UnmanagedComponent, "me")
    other = make_component(cast.UnmanagedComponent, "other", "language")
    got: dict[str, list[str]] = {k: [] for k in ("local", "global", "address", "source", "ops", "entry")}
    me.on_change(cast.local_type_filter(Pose), lambda ch: got["local"].append(ch.id))
    me.on_change(cast.global_type_filter(Pose, Operation.ADD), lambda ch: got["global"].append(ch.id))
    me.on_change(cast.address_filter("a", subarchitecture="language"), lambda ch: got["address"].append(ch.id))
    me.on_change(cast.source_filter("other"), lambda ch: got["source"].append(ch.id))
    me.on_change(cast.operation_filter(Operation.OVERWRITE, local=True), lambda ch: got["ops"].append(ch.id))
    me.on_change(
        cast.local_type_filter(Pose, include_entry=True), lambda ch: got["entry"].append(ch.entry(Pose).value.label)
    )
    me.add("m", Pose(label="mine"))
    me.overwrite("m", Pose(label="mine2"))
    other.add("a", Pose())
    other.add("b", Counter())
    me.add("n", Counter())
    wait_for(lambda: len(got["source"]) >= 2 and len(got["entry"]) >= 2)
    me.drain(5)
    assert got == {
        "local": ["m", "m"],
        "global": ["m", "a"],
        "address": ["a"],
        "source": ["a", "b"],
        "ops": ["m"],
        "entry": ["mine", "mine2"],
    }


def test_cancelled_callbacks_stop(make_component: Any) -> None:
    c = make_component(cast.UnmanagedComponent, "c")
    seen: list[str] = []
    handle = c.on_change(cast.local_type_filter(Pose), lambda ch: seen.append(ch.id))
    c.add("a", Pose())
    wait_for(lambda: seen == ["a"])
    handle.cancel()
    assert not handle.active
    c.add("b", Pose())
    marker: list[str] = []
    c.on_change(cast.local_type_filter(Counter), lambda ch: marker.append(ch.id))
    c.add("z", Counter())
    wait_for(lambda: marker == ["z"])
    assert seen == ["a"]


def test_lock_guard_try_lock_and_blocking_wait(make_component: Any) -> None:
    holder = make_component(cast.UnmanagedComponent, "holder")
    other = make_component(cast.UnmanagedComponent, "other")
    holder.add("x", Pose(label="v0"))
    with holder.lock("x", cast.LockMode.ODR) as guard:
        assert guard.depth == 1
        assert not other.try_lock("x")
        with pytest.raises(cast.LockedError, match="locked \\(ODR\\) by component 'holder'"):
            other.get("x", Pose)
        with pytest.raises(cast.DeadlineExceededError):
            other.lock("x", timeout=0.2)
        got: list[int] = []
        waiter = threading.Thread(target=lambda: got.append(other.lock("x", cast.LockMode.O, timeout=10).depth))
        waiter.start()
        time.sleep(0.2)
        assert waiter.is_alive()  # blocked while the lock is held
    waiter.join(10)
    assert got == [1]
    with pytest.raises(cast.LockedError):
        holder.overwrite("x", Pose())
    assert other.unlock("x") == 0
    assert holder.try_lock("x") and holder.try_lock("x")  # re-entrant
    assert holder.unlock("x") == 1


class Manager(cast.ManagedComponent):
    def start(self) -> None:
        self.decisions: list[tuple[str, str, Any]] = []

    def task_adopted(self, task: cast.Task) -> None:
        self.decisions.append(("adopted", task.name, task.data(Pose)))

    def task_rejected(self, task: cast.Task) -> None:
        self.decisions.append(("rejected", task.name, task.reason))


def test_managed_component_tasks(make_component: Any) -> None:
    m = make_component(Manager, "m")
    m.start()
    first = m.propose_task("first", Pose(label="payload"))
    second = m.propose_task("second")
    wait_for(lambda: len(m.decisions) == 1)
    assert m.decisions[0][:2] == ("adopted", "first") and m.decisions[0][2].label == "payload"
    # Task data read with the wrong class names the task and its SA, as an entry read does.
    with pytest.raises(cast.InvalidArgumentError, match=rf"task '{first.task_id}' data in subarchitecture 'vision' "
                       "has type cast.testing.Pose, not cast.testing.Counter"):
        first.data(Counter)
    assert second.state is cast.TaskState.WAITING  # fifo, one at a time
    m.task_complete(first, cast.TaskOutcome.SUCCEEDED, "done")
    wait_for(lambda: len(m.decisions) == 2)
    assert m.decisions[1] == ("adopted", "second", None)
    m.retract_task(second)
    with pytest.raises(cast.NotFoundError):
        m.task_complete(second)


class Slow(cast.UnmanagedComponent):
    max_pending_callbacks = 16


def test_a_slow_component_lags_without_blocking_writers_and_is_told_past_the_history(make_component: Any) -> None:
    slow = make_component(Slow, "slow", "language")
    writer = make_component(cast.UnmanagedComponent, "w")
    errors: list[cast.CastError] = []
    slow.watch_failed = errors.append  # type: ignore[method-assign]
    blocker = threading.Event()
    seen: list[int] = []

    def callback(change: cast.WorkingMemoryChange) -> None:
        blocker.wait(30)
        seen.append(change.revision)

    # include_entry makes the events big enough to fill the transport's flow-control windows.
    slow.on_change(cast.global_type_filter(Pose, include_entry=True), callback)
    for i in range(40):  # within the history (64 events): delivered late, but all of them
        writer.add(f"e{i}", Pose())
    blocker.set()
    wait_for(lambda: len(seen) == 40, timeout=20)
    assert seen == list(range(1, 41))
    blocker.clear()
    for i in range(40, 1500):  # far past the history while the callback is stuck: writers go on
        writer.add(f"e{i}", Pose(tags=["x" * 16384]))
    blocker.set()
    wait_for(lambda: errors, timeout=20)
    assert isinstance(errors[0], cast.HistoryExpiredError)
    assert seen == sorted(seen) and len(set(seen)) == len(seen)  # what did arrive: in order, once


def test_task_entries_are_the_servers_readable_by_all_written_by_no_component(make_component: Any) -> None:
    from cast.v1.task_manager_pb2 import Task as TaskPb

    m = make_component(Manager, "m")
    m.start()
    other = make_component(cast.UnmanagedComponent, "other")
    boss = make_component(cast.UnmanagedComponent, "boss", "language", privileged=True)
    task = m.propose_task("work")
    wait_for(lambda: len(m.decisions) == 1)
    before = other.get_entry(task.task_id, TaskPb)
    assert before.value.name == "work"
    for who in (other, boss, m):  # same SA, privileged, and the task's own proposer
        with pytest.raises(cast.PermissionDeniedError, match="cast.v1.Task entries belong to the server"):
            who.overwrite(task.task_id, Pose(label="forged"), subarchitecture="vision")
        with pytest.raises(cast.PermissionDeniedError, match="belong to the server"):
            who.delete_entry(task.task_id, subarchitecture="vision")
        with pytest.raises(cast.PermissionDeniedError, match="belong to the server"):
            who.try_lock(task.task_id, cast.LockMode.O, subarchitecture="vision")
        with pytest.raises(cast.PermissionDeniedError, match="belong to the server"):
            who.add(who.new_id(), TaskPb(name="fake"), subarchitecture="vision")
        with pytest.raises(cast.PermissionDeniedError, match="batch operation 0: .*belong to the server"):
            who.batch([("delete", task.task_id, None)], subarchitecture="vision")
    after = other.get_entry(task.task_id, TaskPb)
    assert (after.version, after.value) == (before.version, before.value)


def test_a_value_that_does_not_decode_is_an_invalid_argument_error_naming_the_entry(make_component: Any) -> None:
    # Stored before anyone registered its type (so the server could not check it): no protobuf error
    # reaches the component, whichever way it reads the entry.
    writer = Identity("raw", "vision")
    make_component.system.host.add(writer, "vision", "bad", "cast.testing.Counter", b"\xff\xff\xff\xff")
    make_component.system.durable_sync()
    c = make_component(cast.UnmanagedComponent, "c")
    changes: list[cast.WorkingMemoryChange] = []
    c.on_change(cast.local_type_filter(Counter, include_entry=True), changes.append)
    pattern = r"entry 'bad' in subarchitecture 'vision' does not parse as cast.testing.Counter"
    with pytest.raises(cast.InvalidArgumentError, match=pattern):
        c.get("bad", Counter)
    with pytest.raises(cast.InvalidArgumentError, match=pattern):
        c.get_entry("bad", Counter)
    with pytest.raises(cast.InvalidArgumentError, match=pattern):
        c.get_all(Counter)
    make_component.system.host.overwrite(writer, "vision", "bad", "cast.testing.Counter", b"\x0a\x05ab")
    wait_for(lambda: len(changes) == 1)
    with pytest.raises(cast.InvalidArgumentError, match=pattern):
        changes[0].entry(Counter)

