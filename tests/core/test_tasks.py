"""Task managers and their policies, on the core directly."""

from __future__ import annotations

from typing import Any

import pytest

from cast.core.policies import Decision, TaskPolicy, make_policy
from cast.core.records import Identity
from cast.core.system import TASK_TYPE, System
from cast.core.tasks import TaskOutcome, TaskState
from cast.errors import InvalidArgumentError, LockedError, NoSessionError, NotFoundError, PermissionDeniedError

A = Identity("a", "vision")
B = Identity("b", "vision")


def system(policy: str = "always", **options: Any) -> System:
    sys = System("t", ["vision"], {"vision": make_policy(policy, options)})
    for who in (A, B):  # tasks need a live session
        sys.sessions.register(who, "python", "managed", 1, "h")
    return sys


def states(sys: System, who: Identity) -> list[tuple[str, TaskState]]:
    return [(t.name, t.state) for t in sys.tasks.take_decisions(who.component_id)]


def test_always_adopts_every_proposal_and_records_it_in_the_wm() -> None:
    sys = system()
    task = sys.tasks.propose(A, "look")
    assert task.state is TaskState.ADOPTED
    assert states(sys, A) == [("look", TaskState.ADOPTED)]
    entries = sys.host.get_by_type(A, "vision", TASK_TYPE)[0]
    assert [e.id for e in entries] == [task.task_id]
    ops = [(e.operation.name, e.id) for e in sys.host.events_since("vision", 1)]
    assert ops == [("ADD", task.task_id), ("OVERWRITE", task.task_id)]  # decisions are events
    sys.tasks.complete(A, task.task_id, TaskOutcome.SUCCEEDED, "done")
    assert sys.host.get_by_type(A, "vision", TASK_TYPE)[0] == []
    assert sys.tasks.counters["vision"]["completed"] == 1


def test_fifo_adopts_in_order_up_to_max_concurrent() -> None:
    sys = system("fifo", max_concurrent=2)
    t = [sys.tasks.propose(A if i % 2 else B, f"t{i}") for i in range(5)]
    assert [x.state for x in t] == [TaskState.ADOPTED] * 2 + [TaskState.WAITING] * 3
    sys.tasks.complete(B, t[0].task_id, TaskOutcome.SUCCEEDED)
    assert t[2].state is TaskState.ADOPTED and t[3].state is TaskState.WAITING
    sys.tasks.retract(A, t[3].task_id)  # a waiting task may be retracted
    sys.tasks.complete(A, t[1].task_id, TaskOutcome.FAILED)
    assert t[4].state is TaskState.ADOPTED
    assert [n for n, _ in states(sys, B)] == ["t0", "t2", "t4"]


def test_fifo_rejects_past_max_waiting() -> None:
    sys = system("fifo", max_concurrent=1, max_waiting=1)
    sys.tasks.propose(A, "run")
    sys.tasks.propose(A, "wait")
    late = sys.tasks.propose(A, "late")
    assert late.state is TaskState.REJECTED and "queue full" in late.reason


def test_priority_adopts_the_highest_first_ties_in_order() -> None:
    sys = system("priority", max_concurrent=1)
    first = sys.tasks.propose(A, "first", priority=0)
    low = sys.tasks.propose(A, "low", priority=1)
    high = sys.tasks.propose(A, "high", priority=9)
    high2 = sys.tasks.propose(A, "high2", priority=9)
    assert first.state is TaskState.ADOPTED
    sys.tasks.complete(A, first.task_id, TaskOutcome.SUCCEEDED)
    assert high.state is TaskState.ADOPTED and high2.state is TaskState.WAITING
    sys.tasks.complete(A, high.task_id, TaskOutcome.SUCCEEDED)
    assert high2.state is TaskState.ADOPTED and low.state is TaskState.WAITING


def test_exclusive_runs_one_task_and_rejects_the_rest_while_busy() -> None:
    sys = system("exclusive")
    one = sys.tasks.propose(A, "one")
    two = sys.tasks.propose(B, "two")
    assert one.state is TaskState.ADOPTED
    assert two.state is TaskState.REJECTED and "busy" in two.reason
    assert states(sys, B) == [("two", TaskState.REJECTED)]
    sys.tasks.complete(A, one.task_id, TaskOutcome.SUCCEEDED)
    assert sys.tasks.propose(B, "three").state is TaskState.ADOPTED


class OnlyNamed(TaskPolicy):
    """A user policy: adopts tasks called 'ok', rejects the others."""

    name = "only-named"

    def decide(self, waiting: Any, adopted: Any, wm: Any) -> Decision:
        return Decision(
            adopt=[t for t in waiting if t.name == "ok"],
            reject=[(t, "not ok") for t in waiting if t.name != "ok"],
        )


def test_user_policy_class_by_module_path() -> None:
    policy = make_policy(f"{__name__}:OnlyNamed")
    sys = System("t", ["vision"], {"vision": policy})
    sys.sessions.register(A, "python", "managed", 1, "h")
    assert sys.tasks.propose(A, "ok").state is TaskState.ADOPTED
    assert sys.tasks.propose(A, "nope").state is TaskState.REJECTED


def test_tasks_of_an_ended_session_are_released_and_others_move_up() -> None:
    sys = system("fifo", max_concurrent=1)
    session = sys.sessions.register(A, "python", "managed", 1, "h")
    mine = sys.tasks.propose(A, "mine")
    theirs = sys.tasks.propose(B, "theirs")
    assert theirs.state is TaskState.WAITING
    sys.sessions.end(session)
    assert mine.state is TaskState.RETRACTED
    assert theirs.state is TaskState.ADOPTED
    assert [t.task_id for t in sys.tasks.tasks("vision")] == [theirs.task_id]


def test_task_errors() -> None:
    sys = system("fifo", max_concurrent=1)
    running = sys.tasks.propose(A, "run")
    waiting = sys.tasks.propose(A, "wait")
    with pytest.raises(PermissionDeniedError, match="proposed by 'a'"):
        sys.tasks.complete(B, running.task_id, TaskOutcome.SUCCEEDED)
    with pytest.raises(LockedError, match="waiting, not adopted"):
        sys.tasks.complete(A, waiting.task_id, TaskOutcome.SUCCEEDED)
    with pytest.raises(NotFoundError):
        sys.tasks.retract(A, "task-999")
    with pytest.raises(InvalidArgumentError):
        sys.tasks.propose(A, "")


@pytest.mark.parametrize(
    ("policy", "options", "words"),
    [
        ("sometimes", {}, "unknown task manager policy 'sometimes'"),
        ("fifo", {"max_concurrent": -1}, "max_concurrent must be a whole number"),
        ("always", {"max_concurrent": 2}, "takes no options"),
        ("no.such.module:Policy", {}, "cannot be loaded"),
    ],
)
def test_bad_policies(policy: str, options: dict[str, Any], words: str) -> None:
    with pytest.raises(InvalidArgumentError, match=words):
        make_policy(policy, options)


def test_a_component_without_a_live_session_may_not_propose_and_nothing_is_left_behind() -> None:
    sys = System("t", ["vision"], {"vision": make_policy("fifo", {"max_concurrent": 1})})
    with pytest.raises(NoSessionError, match="component 'a' .* has no live session, so it may not propose task"):
        sys.tasks.propose(A, "work")
    assert sys.tasks.tasks() == [] and sys.host.get_by_type(A, "vision", TASK_TYPE)[0] == []
    session = sys.sessions.register(A, "python", "managed", 1, "h")
    task = sys.tasks.propose(A, "work")
    assert task.state is TaskState.ADOPTED
    sys.sessions.end(session)  # its end releases the task, so the one slot is free again
    assert sys.tasks.tasks() == []
    with pytest.raises(NoSessionError):
        sys.tasks.propose(A, "again")


def test_a_session_that_ends_while_a_task_is_proposed_leaves_no_task() -> None:
    sys = system("fifo", max_concurrent=1)
    checks = iter([True, False])  # live when asked first, ended by the time the task exists
    sys.tasks.session_live = lambda component: next(checks)
    with pytest.raises(NoSessionError):
        sys.tasks.propose(A, "raced")
    assert sys.tasks.tasks() == []
