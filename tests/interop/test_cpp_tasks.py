"""A C++ managed component's tasks through the task manager, under each policy, next to Python ones."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

import cast
from cast.v1 import task_manager_pb2 as tm_pb2
from tests.interop.cpp_support import CppProbe, CppProcess


def system(policy: dict[str, Any]) -> dict[str, Any]:
    return {"system": "tasks", "subarchitectures": {"vision": {"task_manager": policy}, "motor": {}}}


@pytest.fixture
def managed(server_factory: Any) -> Iterator[Any]:
    """A cast_probe (a C++ ManagedComponent) on a server whose vision TM has the given policy."""
    started: list[CppProbe] = []

    def start(policy: dict[str, Any], component_id: str = "ctasks") -> tuple[CppProbe, Any]:
        handle = server_factory(system(policy))
        probe = CppProbe(handle.env(component_id, "vision"))
        started.append(probe)
        probe.ready()
        return probe, handle

    yield start
    for probe in started:
        probe.close()


def decisions(probe: CppProbe, count: int, timeout_ms: int = 15000) -> list[dict[str, Any]]:
    """The decisions the C++ hooks received so far (waiting for at least ``count``)."""
    got: list[dict[str, Any]] = probe.ok("decisions", count, timeout_ms, timeout=timeout_ms / 1000 + 10)["decisions"]
    assert all(d["on_dispatcher"] for d in got), "hooks run on the dispatcher thread"
    return got


def names(ds: list[dict[str, Any]], state: str) -> list[str]:
    return [d["name"] for d in ds if d["state"] == state]


def test_always_adopts_everything(managed: Any) -> None:
    c, _ = managed({"policy": "always"})
    ids = {name: c.ok("propose", name, 0, "Counter", {"writer": "c", "value": "7"})["task_id"] for name in "abc"}
    ds = decisions(c, 3)
    assert sorted(names(ds, "ADOPTED")) == ["a", "b", "c"]
    assert all(d["data"] == {"writer": "c", "value": "7"} for d in ds), "the payload reaches the hook"
    assert all(d["component"] == "ctasks" and d["subarchitecture"] == "vision" for d in ds)
    for name in "abc":
        c.ok("complete", ids[name], "SUCCEEDED", "done")
    c.fails("NotFoundError", "complete", "no-such-task", "SUCCEEDED", "x")
    assert c.quit() == 0


def test_fifo_adopts_up_to_max_concurrent_in_order(managed: Any) -> None:
    c, _ = managed({"policy": "fifo", "max_concurrent": 2})
    ids = {name: c.ok("propose", name, 0)["task_id"] for name in "abcd"}
    assert names(decisions(c, 2), "ADOPTED") == ["a", "b"]
    time.sleep(0.5)
    assert len(decisions(c, 0, 0)) == 2, "c and d wait while two run"
    c.ok("complete", ids["a"], "SUCCEEDED", "")
    assert names(decisions(c, 3), "ADOPTED") == ["a", "b", "c"]
    c.ok("retract", ids["d"])  # withdrawn while waiting: never adopted
    c.ok("complete", ids["b"], "FAILED", "no luck")
    c.ok("complete", ids["c"], "ABANDONED", "")
    time.sleep(0.5)
    assert names(decisions(c, 0, 0), "ADOPTED") == ["a", "b", "c"]
    assert c.quit() == 0


def test_fifo_rejects_past_its_queue(managed: Any) -> None:
    c, _ = managed({"policy": "fifo", "max_concurrent": 1, "max_waiting": 1})
    for name in "abc":
        c.ok("propose", name, 0)
    ds = decisions(c, 2)
    assert names(ds, "ADOPTED") == ["a"]
    rejected = [d for d in ds if d["state"] == "REJECTED"]
    assert [d["name"] for d in rejected] == ["c"]
    assert "queue full" in rejected[0]["reason"]
    assert c.quit() == 0


def test_priority_adopts_the_highest_priority_first(managed: Any) -> None:
    c, _ = managed({"policy": "priority", "max_concurrent": 1})
    first = c.ok("propose", "first", 0)["task_id"]
    assert names(decisions(c, 1), "ADOPTED") == ["first"]
    ids = {name: c.ok("propose", name, prio)["task_id"] for name, prio in (("low", 1), ("high", 9), ("mid", 5))}
    c.ok("complete", first, "SUCCEEDED", "")
    assert names(decisions(c, 2), "ADOPTED") == ["first", "high"]
    c.ok("complete", ids["high"], "SUCCEEDED", "")
    assert names(decisions(c, 3), "ADOPTED") == ["first", "high", "mid"]
    c.ok("complete", ids["mid"], "SUCCEEDED", "")
    assert names(decisions(c, 4), "ADOPTED") == ["first", "high", "mid", "low"]
    assert c.quit() == 0


def test_exclusive_rejects_while_busy_across_languages(managed: Any) -> None:
    c, handle = managed({"policy": "exclusive"})
    running = c.ok("propose", "cpp-job", 0)["task_id"]
    assert names(decisions(c, 1), "ADOPTED") == ["cpp-job"]

    class PyManaged(cast.ManagedComponent):
        def start(self) -> None:
            self.seen: list[cast.Task] = []
            self.event = threading.Event()

        def task_adopted(self, task: cast.Task) -> None:
            self.seen.append(task)
            self.event.set()

        def task_rejected(self, task: cast.Task) -> None:
            self.seen.append(task)
            self.event.set()

    py = handle.connect("pytasks", "vision", cls=PyManaged)
    try:
        py.start()
        py.propose_task("py-job")
        assert py.event.wait(10)
        assert py.seen[0].state is cast.TaskState.REJECTED
        assert "cpp-job" in py.seen[0].reason, "the rejection names the running task"
        c.ok("propose", "cpp-second", 0)
        ds = decisions(c, 2)
        assert names(ds, "REJECTED") == ["cpp-second"]
        c.ok("complete", running, "SUCCEEDED", "")
        py.event.clear()
        py.propose_task("py-job-2")
        assert py.event.wait(10)
        assert py.seen[-1].state is cast.TaskState.ADOPTED
    finally:
        py._cast_close()
    assert c.quit() == 0


def test_autonomous_cpp_tasker_under_fifo(server_factory: Any) -> None:
    """cast_test_tasker proposes on start and works only on what the TM adopts (fifo, two at a time)."""
    handle = server_factory(system({"policy": "fifo", "max_concurrent": 2}))
    watcher = handle.connect("pywatch", "vision")
    adopted_rev: dict[str, int] = {}
    completed_rev: dict[str, int] = {}

    def on_task(change: cast.WorkingMemoryChange) -> None:
        # Task records are entries of type cast.v1.Task: every decision is a change event.
        task = change.entry(tm_pb2.Task).value
        if task.state == tm_pb2.TASK_STATE_ADOPTED:
            adopted_rev.setdefault(task.name, change.revision)
        elif task.state == tm_pb2.TASK_STATE_COMPLETED:
            completed_rev.setdefault(task.name, change.revision)

    watcher.on_change(cast.local_type_filter(tm_pb2.Task, include_entry=True), on_task)
    tasker = CppProcess("cast_test_tasker", handle.env("ctasker", "vision", args={"tasks": 5, "work_ms": 300}))
    try:
        lines: list[dict[str, Any]] = []
        while len([x for x in lines if "completed" in x]) < 5:
            lines.append(tasker.next_json(30))
        proposed = [x["proposed"] for x in lines if "proposed" in x]
        adopted = [x["adopted"] for x in lines if "adopted" in x]
        assert proposed == [f"t{i}" for i in range(5)]
        assert adopted == proposed, "fifo adopts in proposal order"
        # The last completion may still be on its way to the Python watcher.
        deadline = time.monotonic() + 10
        while len(completed_rev) < 5 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert watcher.drain(10)
        assert sorted(completed_rev) == proposed
        # Never more than two at once: task i+2 is adopted only after task i or i+1 completed.
        for i in range(3):
            assert adopted_rev[f"t{i + 2}"] > min(completed_rev[f"t{i}"], completed_rev[f"t{i + 1}"])
        tasker.terminate()
        assert tasker.wait(20) == 0, tasker.output()
    finally:
        watcher._cast_close()
        tasker.close()
