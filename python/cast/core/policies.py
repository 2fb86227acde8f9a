"""Task manager policies: small classes that decide which proposed tasks run.

A policy sees the waiting tasks (oldest first) and the adopted ones of its SA,
and a read-only view of the SA's working memory, and returns which waiting
tasks to adopt and which to reject; the rest keep waiting. It is called after
every proposal, retraction and completion. A user names their own class in
the configuration (``policy: my_pkg.module:MyPolicy``).
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

from cast.core.records import EntryRecord
from cast.errors import InvalidArgumentError

__all__ = [
    "AlwaysPolicy",
    "Decision",
    "ExclusivePolicy",
    "FifoPolicy",
    "PriorityPolicy",
    "TaskPolicy",
    "TaskView",
    "WorkingMemoryView",
    "make_policy",
]


class TaskView(Protocol):
    """What a policy may read of a task."""

    @property
    def task_id(self) -> str: ...  # noqa: D102
    @property
    def name(self) -> str: ...  # noqa: D102
    @property
    def component(self) -> str: ...  # noqa: D102
    @property
    def priority(self) -> int: ...  # noqa: D102


class WorkingMemoryView(Protocol):
    """Read-only access to the policy's SA working memory."""

    def get_by_type(self, type_name: str, limit: int = 0) -> list[EntryRecord]:  # noqa: D102
        ...

    def entry_count(self) -> int:  # noqa: D102
        ...


@dataclass
class Decision:
    """What a policy decided: tasks to adopt, and tasks to reject with a reason each."""

    adopt: list[Any] = field(default_factory=list)
    reject: list[tuple[Any, str]] = field(default_factory=list)


class TaskPolicy:
    """Base class of task manager policies; subclasses override :meth:`decide`."""

    name: ClassVar[str] = "custom"

    def __init__(self, **options: Any) -> None:
        if options:
            raise InvalidArgumentError(
                f"task manager policy '{self.name}' takes no options, got: {', '.join(sorted(options))}"
            )

    def decide(self, waiting: Sequence[Any], adopted: Sequence[Any], wm: WorkingMemoryView) -> Decision:
        """Return which of ``waiting`` (oldest first) to adopt and which to reject."""
        raise NotImplementedError

    def describe(self) -> str:
        """Short human description used by ``cast tasks`` and the status view."""
        return self.name


class AlwaysPolicy(TaskPolicy):
    """Adopt every task at once."""

    name = "always"

    def decide(self, waiting: Sequence[Any], adopted: Sequence[Any], wm: WorkingMemoryView) -> Decision:
        """Adopt all waiting tasks."""
        return Decision(adopt=list(waiting))


def _positive(policy: str, key: str, value: Any) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise InvalidArgumentError(f"task manager policy '{policy}': {key} must be a whole number >= 0, got {value!r}")
    return value


class FifoPolicy(TaskPolicy):
    """Adopt up to ``max_concurrent`` tasks in proposal order; the others wait.

    ``max_waiting`` (0 = unbounded) rejects proposals once that many wait.
    """

    name = "fifo"

    def __init__(self, max_concurrent: int = 1, max_waiting: int = 0) -> None:
        self.max_concurrent = max(1, _positive(self.name, "max_concurrent", max_concurrent))
        self.max_waiting = _positive(self.name, "max_waiting", max_waiting)

    def _order(self, waiting: Sequence[Any]) -> list[Any]:
        return list(waiting)

    def decide(self, waiting: Sequence[Any], adopted: Sequence[Any], wm: WorkingMemoryView) -> Decision:
        """Adopt in order while slots are free; reject past ``max_waiting``."""
        ordered = self._order(waiting)
        free = max(0, self.max_concurrent - len(adopted))
        decision = Decision(adopt=ordered[:free])
        rest = ordered[free:]
        if self.max_waiting:
            # Past the queue's length the last in policy order lose (newest, or lowest priority).
            decision.reject = [(t, f"queue full ({self.max_waiting} tasks waiting)") for t in rest[self.max_waiting :]]
        return decision

    def describe(self) -> str:
        """E.g. ``fifo(max_concurrent=2)``."""
        return f"{self.name}(max_concurrent={self.max_concurrent})"


class PriorityPolicy(FifoPolicy):
    """Like fifo, but the highest ``priority`` waiting task is adopted first (ties: oldest first)."""

    name = "priority"

    def _order(self, waiting: Sequence[Any]) -> list[Any]:
        # sorted() is stable, so equal priorities keep proposal order.
        return sorted(waiting, key=lambda t: -t.priority)


class ExclusivePolicy(TaskPolicy):
    """One task at a time in the SA; proposals made while one runs are rejected (no queue)."""

    name = "exclusive"

    def decide(self, waiting: Sequence[Any], adopted: Sequence[Any], wm: WorkingMemoryView) -> Decision:
        """Adopt the oldest waiting task if none runs; reject the others."""
        decision = Decision()
        queue = list(waiting)
        if not adopted and queue:
            decision.adopt.append(queue.pop(0))
        busy = adopted[0] if adopted else (decision.adopt[0] if decision.adopt else None)
        for task in queue:
            assert busy is not None  # queue is non-empty only when something runs or was just adopted
            decision.reject.append((task, f"busy: task '{busy.name}' ({busy.task_id}) is running"))
        return decision


BUILTIN_POLICIES: dict[str, type[TaskPolicy]] = {
    cls.name: cls for cls in (AlwaysPolicy, FifoPolicy, PriorityPolicy, ExclusivePolicy)
}


def make_policy(policy: str, options: dict[str, Any] | None = None) -> TaskPolicy:
    """Build a policy by built-in name or ``module:Class``; INVALID_ARGUMENT with a hint if unknown."""
    options = dict(options or {})
    cls: Any = BUILTIN_POLICIES.get(policy)
    if cls is None:
        if ":" not in policy:
            raise InvalidArgumentError(
                f"unknown task manager policy '{policy}': use one of {', '.join(BUILTIN_POLICIES)} "
                "or 'module:Class' for your own"
            )
        module_name, _, class_name = policy.partition(":")
        try:
            cls = getattr(importlib.import_module(module_name), class_name)
        except (ImportError, AttributeError) as exc:
            raise InvalidArgumentError(f"task manager policy '{policy}' cannot be loaded: {exc}") from exc
        if not (isinstance(cls, type) and issubclass(cls, TaskPolicy)):
            raise InvalidArgumentError(f"task manager policy '{policy}' is not a subclass of cast.TaskPolicy")
    try:
        instance: TaskPolicy = cls(**options)
    except TypeError as exc:
        raise InvalidArgumentError(f"task manager policy '{policy}': bad options {options}: {exc}") from exc
    return instance
