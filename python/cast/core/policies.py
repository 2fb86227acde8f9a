"""Task manager policies: small classes that decide which proposed tasks run.

A policy sees the waiting tasks (oldest first) and the adopted ones of its SA,
and a read-only view of the SA's working memory, and returns which waiting
tasks to adopt and which to reject; the rest keep waiting. It is called after
every proposal, retraction and completion. A user names their own class in
the configuration (``policy: my_pkg.module:MyPolicy``).

Each policy class declares the options it takes (:class:`PolicyOption`: name,
type, default, description) in ``options``; ``cast check``, the configuration's
JSON Schema and :func:`make_policy` all read that one declaration.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

from cast.core.records import EntryRecord
from cast.errors import InvalidArgumentError

__all__ = [
    "BUILTIN_POLICIES",
    "DEFAULT_POLICY",
    "AlwaysPolicy",
    "Decision",
    "ExclusivePolicy",
    "FifoPolicy",
    "PolicyOption",
    "PriorityPolicy",
    "TaskPolicy",
    "TaskView",
    "WorkingMemoryView",
    "make_policy",
    "policy_class",
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


# JSON Schema's names for the option types a policy may declare (what a YAML scalar can be).
_JSON_TYPES: dict[type, str] = {bool: "boolean", int: "integer", float: "number", str: "string"}
_PHRASES: dict[type, str] = {
    bool: "must be true or false", int: "must be a whole number", float: "must be a number", str: "must be text",
}


@dataclass(frozen=True)
class PolicyOption:
    """One option a task manager policy takes: its key in ``task_manager:``, type, default and meaning.

    ``value_type`` is ``bool``, ``int``, ``float`` or ``str``; ``minimum`` bounds a number.
    """

    name: str
    value_type: type
    default: Any
    description: str
    minimum: float | None = None

    def __post_init__(self) -> None:
        if self.value_type not in _JSON_TYPES:
            raise TypeError(f"policy option '{self.name}': value_type must be bool, int, float or str")

    def json_schema(self) -> dict[str, Any]:
        """The option as a JSON Schema property (what editors show and the configuration's schema holds)."""
        out: dict[str, Any] = {"description": self.description, "type": _JSON_TYPES[self.value_type]}
        if self.minimum is not None:
            out["minimum"] = self.minimum
        out["default"] = self.default
        return out

    def problem(self, value: Any) -> str | None:
        """What is wrong with ``value`` for this option (``must be ..., not X``), or None if it is right.

        Accepts exactly what :meth:`json_schema` accepts (YAML's 2.0 is not a whole number here).
        """
        phrase = _PHRASES[self.value_type]
        if self.value_type is bool:
            ok = isinstance(value, bool)
        elif self.value_type is str:
            ok = isinstance(value, str)
        else:
            wanted = int if self.value_type is int else (int, float)
            ok = isinstance(value, wanted) and not isinstance(value, bool)
        if self.minimum is not None:
            phrase += f" >= {self.minimum:g}"
            # "not below" rather than ">=" so that a NaN passes, as it does JSON Schema's minimum.
            ok = ok and not value < self.minimum
        return None if ok else f"{phrase}, not {value!r}"


class TaskPolicy:
    """Base class of task manager policies; subclasses override :meth:`decide`.

    ``options`` declares what the policy takes in the configuration; a class
    that leaves it ``None`` (written before options were declared) gets its
    options passed to its constructor unchecked, as before.
    """

    name: ClassVar[str] = "custom"
    options: ClassVar[tuple[PolicyOption, ...] | None] = None

    def __init__(self, **options: Any) -> None:
        if options:
            raise InvalidArgumentError(
                f"task manager policy '{self.name}' takes no options, got: {', '.join(sorted(options))}"
            )

    @classmethod
    def check_options(cls, policy: str, options: Mapping[str, Any]) -> None:
        """Raise INVALID_ARGUMENT naming each option the class does not declare or whose value is wrong.

        Nothing is checked for a class that declares no ``options`` (None): its constructor decides.
        """
        if cls.options is None:
            return
        declared = {o.name: o for o in cls.options}
        if options and not declared:
            raise InvalidArgumentError(
                f"task manager policy '{policy}' takes no options, got: {', '.join(sorted(options))}"
            )
        wrong: list[str] = []
        for key, value in options.items():
            option = declared.get(key)
            if option is None:
                close = difflib.get_close_matches(key, sorted(declared), n=1, cutoff=0.6)
                hint = f"did you mean '{close[0]}'?" if close else f"it takes {', '.join(declared)}"
                wrong.append(f"{key} is not one of its options ({hint})")
            elif (problem := option.problem(value)) is not None:
                wrong.append(f"{key} {problem}")
        if wrong:
            raise InvalidArgumentError(f"task manager policy '{policy}': {'; '.join(wrong)}")

    def decide(self, waiting: Sequence[Any], adopted: Sequence[Any], wm: WorkingMemoryView) -> Decision:
        """Return which of ``waiting`` (oldest first) to adopt and which to reject."""
        raise NotImplementedError

    def describe(self) -> str:
        """Short human description used by ``cast tasks`` and the status view."""
        return self.name


class AlwaysPolicy(TaskPolicy):
    """Adopt every task at once."""

    name = "always"
    options = ()

    def decide(self, waiting: Sequence[Any], adopted: Sequence[Any], wm: WorkingMemoryView) -> Decision:
        """Adopt all waiting tasks."""
        return Decision(adopt=list(waiting))


class FifoPolicy(TaskPolicy):
    """Adopt up to ``max_concurrent`` tasks in proposal order; the others wait.

    ``max_waiting`` (0 = unbounded) rejects proposals once that many wait.
    """

    name = "fifo"
    options = (
        PolicyOption("max_concurrent", int, 1, "Tasks adopted (running) at once; 0 counts as 1.", minimum=0),
        PolicyOption("max_waiting", int, 0, "Tasks that may wait; past that the last in policy order are "
                     "rejected (0: no bound).", minimum=0),
    )

    def __init__(self, max_concurrent: int = 1, max_waiting: int = 0) -> None:
        self.check_options(self.name, {"max_concurrent": max_concurrent, "max_waiting": max_waiting})
        self.max_concurrent = max(1, max_concurrent)
        self.max_waiting = max_waiting

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
    options = ()

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
DEFAULT_POLICY = AlwaysPolicy.name  # an SA whose configuration names no policy


def policy_class(policy: str) -> type[TaskPolicy]:
    """The class of a built-in policy name or ``module:Class``; INVALID_ARGUMENT with a hint if there is none."""
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
    found: type[TaskPolicy] = cls
    return found


def make_policy(policy: str, options: Mapping[str, Any] | None = None) -> TaskPolicy:
    """Build a policy by built-in name or ``module:Class`` with its options; INVALID_ARGUMENT saying what is wrong."""
    options = dict(options or {})
    cls = policy_class(policy)
    cls.check_options(policy, options)
    try:
        instance: TaskPolicy = cls(**options)
    except TypeError as exc:
        raise InvalidArgumentError(f"task manager policy '{policy}': bad options {options}: {exc}") from exc
    return instance
