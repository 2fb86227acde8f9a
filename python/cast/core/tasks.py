"""Task managers: one per subarchitecture, each with its policy.

The board keeps every live task, asks the SA's policy for decisions after each
change, queues decisions for the proposing component, and publishes every
state change through ``publish`` (the server writes it into the SA's WM as a
``cast.v1.Task`` entry, so decisions are change events any tool can watch).
A decision is handed to its component only once that write is visible, that
is durable when the server waits for its journal: no component acts on a
decision that a crash could undo.
"""

from __future__ import annotations

import enum
import itertools
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

from cast.core.host import MemoryHost
from cast.core.metrics import Metrics
from cast.core.policies import AlwaysPolicy, TaskPolicy
from cast.core.records import EntryRecord, Identity, no_session
from cast.errors import InvalidArgumentError, NoSessionError, NotFoundError, PermissionDeniedError, TaskStateError

__all__ = ["DecisionFeed", "TaskBoard", "TaskOutcome", "TaskRecord", "TaskState"]


class TaskState(enum.IntEnum):
    """Values equal the wire enum ``cast.v1.TaskState``."""

    WAITING = 1
    ADOPTED = 2
    REJECTED = 3
    RETRACTED = 4
    COMPLETED = 5


class TaskOutcome(enum.IntEnum):
    """Values equal the wire enum ``cast.v1.TaskOutcome``."""

    UNSPECIFIED = 0
    SUCCEEDED = 1
    FAILED = 2
    ABANDONED = 3


LIVE = (TaskState.WAITING, TaskState.ADOPTED)


@dataclass
class TaskRecord:
    """One task and where it is in its life."""

    task_id: str
    name: str
    subarchitecture: str
    component: str
    data_type: str
    data: bytes
    priority: int
    state: TaskState
    proposed_ns: int
    outcome: TaskOutcome = TaskOutcome.UNSPECIFIED
    reason: str = ""
    decided_ns: int = 0


class _WMView:
    """Read-only view of one SA's WM for a policy."""

    def __init__(self, host: MemoryHost, sa: str) -> None:
        self._host = host
        self._sa = sa
        self._who = Identity(f"{sa}.task_manager", sa, False)

    def get_by_type(self, type_name: str, limit: int = 0) -> list[EntryRecord]:
        return self._host.get_by_type(self._who, self._sa, type_name, limit)[0]

    def entry_count(self) -> int:
        return self._host.entry_count(self._sa)


Publisher = Callable[[TaskRecord], int]
"""Writes a task's new state into its SA's WM; returns the revision of that write."""


class TaskBoard:
    """The task managers of every SA of a host."""

    def __init__(
        self,
        host: MemoryHost,
        policies: Mapping[str, TaskPolicy] | None = None,
        publish: Publisher | None = None,
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self._host = host
        self._policies: dict[str, TaskPolicy] = {sa: AlwaysPolicy() for sa in host.subarchitectures}
        for sa, policy in (policies or {}).items():
            host.revision(sa)  # NOT_FOUND for an unknown SA
            self._policies[sa] = policy
        self._publish = publish
        self._clock = clock
        self._mutex = threading.RLock()
        self._ids = itertools.count(1)
        self._live: dict[str, TaskRecord] = {}  # insertion order = proposal order
        # Per component: (decision, SA, revision of its write), handed out once the revision is visible.
        self._decisions: dict[str, list[tuple[TaskRecord, str, int]]] = {}
        self._listeners: list[Callable[[str], None]] = []
        # Whether a component has a live session (cast.core.sessions); None: no sessions (bare core).
        self.session_live: Callable[[str], bool] | None = None
        self.metrics: Metrics | None = None  # counts decisions per component too (cast.core.metrics); None: off
        self.counters: dict[str, dict[str, int]] = {
            sa: {"proposed": 0, "adopted": 0, "rejected": 0, "retracted": 0, "completed": 0}
            for sa in host.subarchitectures
        }

    def policy(self, sa: str) -> TaskPolicy:
        """The policy of one SA."""
        self._host.revision(sa)
        return self._policies[sa]

    def add_listener(self, listener: Callable[[str], None]) -> None:
        """Call ``listener(component_id)`` when decisions are queued for that component."""
        self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[str], None]) -> None:
        """Stop calling a listener."""
        if listener in self._listeners:
            self._listeners.remove(listener)

    def propose(
        self, who: Identity, name: str, data_type: str = "", data: bytes = b"", priority: int = 0
    ) -> TaskRecord:
        """Propose a task to the caller's SA task manager; return it (maybe already decided)."""
        if not who.subarchitecture:
            raise PermissionDeniedError(f"{who.describe()} belongs to no SA, so it has no task manager")
        if not name or len(name.encode()) > 256:
            raise InvalidArgumentError("task name must be 1 to 256 bytes")
        sa = who.subarchitecture
        self._host.revision(sa)
        live = self.session_live
        if live is not None and not live(who.component_id):
            raise NoSessionError(no_session(who, f"propose task '{name}'"))
        task = self._propose(who, name, data_type, data, priority)
        if live is not None and not live(who.component_id):
            # The session ended while the task was being proposed, after it released what it held.
            self.release_component(who.component_id)
            raise NoSessionError(no_session(who, f"propose task '{name}'"))
        return task

    def _propose(self, who: Identity, name: str, data_type: str, data: bytes, priority: int) -> TaskRecord:
        sa = who.subarchitecture
        with self._mutex:
            task = TaskRecord(
                f"task-{next(self._ids)}",
                name,
                sa,
                who.component_id,
                data_type,
                data,
                priority,
                TaskState.WAITING,
                self._clock(),
            )
            self._live[task.task_id] = task
            self._count(task, "proposed")
            self._emit(task, queue=False)
            self._decide(sa)
            return task

    def retract(self, who: Identity, task_id: str) -> TaskRecord:
        """Withdraw a waiting or adopted task of the caller."""
        with self._mutex:
            task = self._own(who, task_id)
            self._finish(task, TaskState.RETRACTED, TaskOutcome.UNSPECIFIED, "retracted by its proposer")
            return task

    def complete(self, who: Identity, task_id: str, outcome: TaskOutcome | int, reason: str = "") -> TaskRecord:
        """Report the outcome of an adopted task of the caller: SUCCEEDED, FAILED or ABANDONED."""
        try:
            outcome = TaskOutcome(outcome)
        except ValueError:
            raise InvalidArgumentError(f"unknown task outcome {outcome}: give SUCCEEDED, FAILED or ABANDONED") from None
        if outcome is TaskOutcome.UNSPECIFIED:
            raise InvalidArgumentError("a completed task needs an outcome: SUCCEEDED, FAILED or ABANDONED")
        with self._mutex:
            task = self._own(who, task_id)
            if task.state is not TaskState.ADOPTED:
                raise TaskStateError(
                    f"task '{task_id}' is {task.state.name.lower()}, not adopted: only adopted tasks complete "
                    "(retract a waiting one instead)"
                )
            self._finish(task, TaskState.COMPLETED, TaskOutcome(outcome), reason)
            return task

    def release_component(self, component_id: str) -> list[str]:
        """Retract every live task of a component whose session ended."""
        with self._mutex:
            mine = [t for t in self._live.values() if t.component == component_id]
            for task in mine:
                self._finish(task, TaskState.RETRACTED, TaskOutcome.UNSPECIFIED, "its component's session ended")
            self._decisions.pop(component_id, None)
            return [t.task_id for t in mine]

    def take_decisions(self, component_id: str) -> list[TaskRecord]:
        """Drain the decisions queued for a component (adopted, rejected) whose writes are visible, oldest first."""
        with self._mutex:
            queued = self._decisions.get(component_id)
            if not queued:
                return []
            ready = 0
            for _, sa, revision in queued:
                if revision > self._host.revision(sa):
                    break
                ready += 1
            taken = [task for task, _, _ in queued[:ready]]
            del queued[:ready]
            if not queued:
                del self._decisions[component_id]
            return taken

    def writes_visible(self) -> None:
        """Writes became visible: tell the components whose decisions may now be handed out.

        Only needed when writes become visible after they are made (a journal that writers
        wait for): the host calls it then (``System`` registers it).
        """
        if not self._decisions:
            return
        with self._mutex:
            waiting = list(self._decisions)
        for component_id in waiting:
            for listener in list(self._listeners):
                listener(component_id)

    def tasks(self, sa: str = "") -> list[TaskRecord]:
        """Live tasks (waiting or adopted), oldest first, of one SA or all."""
        if sa:
            self._host.revision(sa)
        with self._mutex:
            return [t for t in self._live.values() if not sa or t.subarchitecture == sa]

    def _own(self, who: Identity, task_id: str) -> TaskRecord:
        task = self._live.get(task_id)
        if task is None:
            raise NotFoundError(f"no live task '{task_id}' (it never existed, or already ended)")
        if task.component != who.component_id:
            raise PermissionDeniedError(f"task '{task_id}' was proposed by '{task.component}', not by {who.describe()}")
        return task

    def _finish(self, task: TaskRecord, state: TaskState, outcome: TaskOutcome, reason: str) -> None:
        task.state, task.outcome, task.reason = state, outcome, reason
        del self._live[task.task_id]
        self._count(task, state.name.lower())
        self._emit(task, queue=False)
        self._decide(task.subarchitecture)

    def _decide(self, sa: str) -> None:
        waiting = [t for t in self._live.values() if t.subarchitecture == sa and t.state is TaskState.WAITING]
        if not waiting:
            return
        adopted = [t for t in self._live.values() if t.subarchitecture == sa and t.state is TaskState.ADOPTED]
        decision = self._policies[sa].decide(waiting, adopted, _WMView(self._host, sa))
        now = self._clock()
        for task in decision.adopt:
            if task.state is TaskState.WAITING:
                task.state, task.decided_ns = TaskState.ADOPTED, now
                self._count(task, "adopted", now - task.proposed_ns)
                self._emit(task, queue=True)
        for task, reason in decision.reject:
            if task.state is TaskState.WAITING:
                task.state, task.decided_ns, task.reason = TaskState.REJECTED, now, reason
                del self._live[task.task_id]
                self._count(task, "rejected")
                self._emit(task, queue=True)

    def _count(self, task: TaskRecord, what: str, wait_ns: int | None = None) -> None:
        """Count what happened to ``task`` per SA, and per component in the metrics."""
        self.counters[task.subarchitecture][what] += 1
        if self.metrics is not None:
            self.metrics.task(task.component, task.subarchitecture, what, wait_ns)

    def _emit(self, task: TaskRecord, queue: bool) -> None:
        revision = self._publish(task) if self._publish is not None else 0
        if queue:
            snapshot = replace(task)
            self._decisions.setdefault(task.component, []).append((snapshot, task.subarchitecture, revision))
            for listener in list(self._listeners):
                listener(task.component)


class DecisionFeed:
    """The task manager's decisions about one component's tasks, handed out once each, oldest first.

    ``wake`` is called (on the thread that decided) whenever new decisions may be ready; the reader
    then takes them (:meth:`take`). Decisions made before the feed opened are handed out too, so a
    component that subscribes late misses none. Over gRPC this is a ``TaskManager.Decisions`` call,
    in process the in-process transport's sink.
    """

    def __init__(self, tasks: TaskBoard, component_id: str, wake: Callable[[], None]) -> None:
        self._tasks = tasks
        self._component_id = component_id
        self._wake = wake
        tasks.add_listener(self._decided)

    def _decided(self, component_id: str) -> None:
        if component_id == self._component_id:
            self._wake()

    def take(self) -> list[TaskRecord]:
        """The decisions ready now, not handed out before."""
        return self._tasks.take_decisions(self._component_id)

    def close(self) -> None:
        """Stop waking the reader."""
        self._tasks.remove_listener(self._decided)
