"""Task manager policies named in a configuration: their decisions, and every decision as a WM event."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from cast.config import load_config
from cast.core.records import Identity, Operation
from cast.core.system import TASK_TYPE, System
from cast.core.tasks import TaskOutcome, TaskRecord, TaskState
from cast.orchestrator.servers import build_system
from cast.v1 import task_manager_pb2
from tests.orchestrator.conftest import Embedded, wait_for, write_config

ALICE = Identity("alice", "sa")
BOB = Identity("bob", "sa")


def system_for(tmp_path: Path, task_manager: dict[str, object]) -> System:
    """A system (as the orchestrator builds it) whose one SA has this task manager configuration."""
    cfg = write_config(tmp_path / "tm.yaml", {"subarchitectures": {"sa": {"task_manager": task_manager}}})
    config = load_config(cfg, environ={})
    system = build_system(config, config.servers[0])
    for who in (ALICE, BOB):  # tasks need a live session
        system.sessions.register(who, "python", "managed", 1, "h")
    return system


def states(system: System, *tasks: TaskRecord) -> list[str]:
    live = {t.task_id: t.state for t in system.tasks.tasks("sa")}
    return [live.get(t.task_id, t.state).name.lower() for t in tasks]


def test_always_adopts_everything(tmp_path: Path) -> None:
    system = system_for(tmp_path, {"policy": "always"})
    tasks = [system.tasks.propose(ALICE, f"t{i}") for i in range(3)]
    assert states(system, *tasks) == ["adopted"] * 3


def test_fifo_adopts_in_order_up_to_max_concurrent(tmp_path: Path) -> None:
    system = system_for(tmp_path, {"policy": "fifo", "max_concurrent": 2})
    board = system.tasks
    t1, t2, t3, t4 = (board.propose(ALICE if i % 2 else BOB, f"t{i}") for i in range(1, 5))
    assert states(system, t1, t2, t3, t4) == ["adopted", "adopted", "waiting", "waiting"]
    board.complete(BOB, t2.task_id, TaskOutcome.SUCCEEDED)
    assert states(system, t3, t4) == ["adopted", "waiting"]  # the oldest waiting one goes first
    board.retract(BOB, t4.task_id)
    board.complete(ALICE, t1.task_id, TaskOutcome.FAILED, "no luck")
    assert [t.task_id for t in board.tasks("sa")] == [t3.task_id]
    assert board.counters["sa"] == {"proposed": 4, "adopted": 3, "rejected": 0, "retracted": 1, "completed": 2}
    assert board.policy("sa").describe() == "fifo(max_concurrent=2)"


def test_fifo_rejects_past_max_waiting(tmp_path: Path) -> None:
    system = system_for(tmp_path, {"policy": "fifo", "max_concurrent": 1, "max_waiting": 1})
    t1, t2, t3 = (system.tasks.propose(ALICE, f"t{i}") for i in range(3))
    assert states(system, t1, t2, t3) == ["adopted", "waiting", "rejected"]
    assert t3.reason == "queue full (1 tasks waiting)"


def test_priority_adopts_the_highest_first_ties_oldest_first(tmp_path: Path) -> None:
    system = system_for(tmp_path, {"policy": "priority", "max_concurrent": 1})
    board = system.tasks
    running = board.propose(ALICE, "running", priority=0)
    low = board.propose(ALICE, "low", priority=1)
    high_a = board.propose(BOB, "high-a", priority=5)
    high_b = board.propose(ALICE, "high-b", priority=5)
    order = []
    current = running
    for _ in range(3):
        board.complete(Identity(current.component, "sa"), current.task_id, TaskOutcome.SUCCEEDED)
        current = next(t for t in board.tasks("sa") if t.state is TaskState.ADOPTED)
        order.append(current.name)
    assert order == ["high-a", "high-b", "low"]
    assert low.task_id and high_a.task_id and high_b.task_id


def test_exclusive_runs_one_task_and_rejects_the_others(tmp_path: Path) -> None:
    system = system_for(tmp_path, {"policy": "exclusive"})
    board = system.tasks
    first = board.propose(ALICE, "first")
    second = board.propose(BOB, "second")
    assert states(system, first, second) == ["adopted", "rejected"]
    assert second.reason == f"busy: task 'first' ({first.task_id}) is running"
    board.complete(ALICE, first.task_id, TaskOutcome.SUCCEEDED)
    third = board.propose(BOB, "third")
    assert states(system, third) == ["adopted"]


def test_user_policy_class_from_the_configuration(tmp_path: Path) -> None:
    system = system_for(tmp_path, {"policy": "orch_policies:PrefixPolicy", "prefix": "ok-"})
    good, bad = system.tasks.propose(ALICE, "ok-1"), system.tasks.propose(ALICE, "nope")
    assert states(system, good, bad) == ["adopted", "rejected"]
    assert bad.reason == "name does not start with 'ok-'"
    assert system.tasks.policy("sa").describe() == "prefix(ok-)"


def test_every_decision_is_a_change_event_in_the_sas_wm(tmp_path: Path) -> None:
    system = system_for(tmp_path, {"policy": "fifo", "max_concurrent": 1, "max_waiting": 1})
    board = system.tasks
    first, second, third = (board.propose(ALICE, n) for n in ("first", "second", "third"))
    board.complete(ALICE, first.task_id, TaskOutcome.SUCCEEDED, "done")
    events = [e for e in system.host.events_since("sa", 1) if e.type == TASK_TYPE or e.operation is Operation.DELETE]
    seen: list[tuple[str, str, str]] = []
    for e in events:
        if e.operation is Operation.DELETE:
            seen.append((e.id, "delete", ""))
            continue
        assert e.entry is not None and e.source_component == "sa.task_manager"
        task = task_manager_pb2.Task.FromString(e.entry.data)
        seen.append((e.id, e.operation.name.lower(), task_manager_pb2.TaskState.Name(task.state)))
    f, s, t = first.task_id, second.task_id, third.task_id
    assert seen == [
        (f, "add", "TASK_STATE_WAITING"), (f, "overwrite", "TASK_STATE_ADOPTED"),
        (s, "add", "TASK_STATE_WAITING"),
        (t, "add", "TASK_STATE_WAITING"), (t, "overwrite", "TASK_STATE_REJECTED"), (t, "delete", ""),
        (f, "overwrite", "TASK_STATE_COMPLETED"), (f, "delete", ""),
        (s, "overwrite", "TASK_STATE_ADOPTED"),
    ]


def test_policies_wired_end_to_end_with_managed_components(
    tmp_path: Path, embedded: Callable[..., Embedded]
) -> None:
    cfg = write_config(tmp_path / "e2e.yaml", {
        "subarchitectures": {
            "work": {
                "task_manager": {"policy": "fifo", "max_concurrent": 1},
                "components": {
                    "producer": {"class": "orch_components:Producer", "args": {"count": 5}},
                    "worker": {"kind": "managed", "class": "orch_components:Worker", "args": {"source_sa": "work"}},
                },
            },
        },
    })
    run = embedded(cfg)
    system = run.system("work")
    who = Identity("test", "work")
    wait_for(lambda: all(system.host.exists(who, "work", f"result-{i}") for i in range(5)), what="every result")
    wait_for(lambda: system.tasks.counters["work"]["completed"] == 5, what="every task completed")
    assert system.tasks.counters["work"]["adopted"] == 5
    adoptions = [e for e in system.host.events_since("work", 1) if e.type == TASK_TYPE and e.entry is not None
                 and task_manager_pb2.Task.FromString(e.entry.data).state == task_manager_pb2.TASK_STATE_ADOPTED]
    assert len(adoptions) == 5
    assert run.stop().exit_code == 0
