"""A whole CAST node without the network: WMs, task managers, sessions, schemas.

The server wraps a :class:`System` in gRPC servicers; in-process components
call it directly; either way every caller goes through its
:class:`cast.core.access.Access`. What the wire adds (its own .proto files, a
task's bytes) is handed in by the server layer (:mod:`cast.server.wire`).
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar

from google.protobuf.descriptor import FileDescriptor

from cast.core.barrier import StartBarrier
from cast.core.host import BatchOp, MemoryHost
from cast.core.journal import Journal
from cast.core.metrics import Metrics
from cast.core.policies import TaskPolicy
from cast.core.records import TASK_TYPE, Identity, Limits, Operation, Quota
from cast.core.schemas import SchemaRegistry
from cast.core.sessions import ComponentInfo, SessionTable
from cast.core.shared import SharedMemory, SharedSettings
from cast.core.tasks import TaskBoard, TaskRecord, TaskState
from cast.core.versions import epoch_floor

__all__ = ["TASK_TYPE", "System"]

_T = TypeVar("_T")


class System:
    """Everything one server hosts, wired together."""

    def __init__(
        self,
        name: str,
        subarchitectures: Sequence[str],
        policies: Mapping[str, TaskPolicy] | None = None,
        limits: Limits | None = None,
        lease_ms: int = 10_000,
        journal: Journal | None = None,
        version_floor: int | None = None,
        quotas: Mapping[str, Quota] | None = None,
        own_files: Sequence[FileDescriptor] = (),
        encode_task: Callable[[TaskRecord], bytes] | None = None,
        metrics: bool = True,
        shared_memory: SharedSettings | None = None,
    ) -> None:
        """Wire the parts together.

        ``own_files`` (the wire's .proto files, preloaded like the well-known
        ones) and ``encode_task`` (a task's bytes in its ``cast.v1.Task``
        entry) come from the server layer (cast.server.wire), so that the core
        knows nothing of the wire. ``metrics``: count what callers do
        (cast.core.metrics; a server's ``--no-metrics`` turns it off).
        ``shared_memory``: large values kept in shared memory for readers on
        this host (cast.core.shared); None or not enabled: none.
        """
        self.name = name
        # The system's own files are the server's, like the well-known ones: client copies are ignored.
        self.schemas = SchemaRegistry(own=own_files)
        self._encode_task = encode_task
        if version_floor is None:
            # Memory only: an earlier run of this server may have given versions nobody can know of
            # now, so this run starts above them (cast.core.versions); a journal knows its floor.
            version_floor = journal.version_floor if journal is not None else epoch_floor()
        self.host = MemoryHost(
            subarchitectures, limits, validator=self.schemas.validate, version_floor=version_floor, quotas=quotas
        )
        settings = shared_memory or SharedSettings(enabled=False)
        # None when turned off: every value is then bytes, as it arrived.
        self.shared = SharedMemory(settings, self.host.limits) if settings.enabled else None
        self.tasks = TaskBoard(self.host, policies, publish=self._publish_task)
        self.metrics = Metrics(name, self.host.subarchitectures, enabled=metrics)
        if self.shared is not None:
            self.metrics.shared = self.shared.snapshot
        self.tasks.metrics = self.metrics.active
        self.sessions = SessionTable(self._session_ended, lease_ms=lease_ms)
        self.barrier = StartBarrier()  # released unless `cast run` holds it (cast.core.barrier)
        # Locks and tasks need a live session: its end is what releases them.
        self.host.session_live = self.tasks.session_live = self.sessions.has_live
        self.started_ns = time.time_ns()
        self.journal = journal
        # Identifies this history of revisions: watchers resume only into the history they saw. A
        # journal keeps it across restarts; without one every start is a new history.
        self.history_id = journal.history_id if journal is not None else secrets.token_hex(8)
        if journal is not None:
            self._restore(journal)

    def _restore(self, journal: Journal) -> None:
        """Load the journal's state, then start journaling every commit and schema."""
        stored = journal.load()
        dropped = self.schemas.restore(stored.schemas)
        if dropped:
            journal.forget_schemas(dropped)
        hosted = set(self.host.subarchitectures)
        for sa, state in stored.wms.items():
            if sa in hosted:  # an SA no longer configured keeps its rows but is not served
                self.host.restore(sa, state.entries, state.deleted, state.revision, state.events)
        # In always and batch a write becomes visible once durable (cast.core.host); in none at once.
        if journal.waits:
            journal.on_durable = self.host.apply_durable
            self.host.add_listener(self.tasks.writes_visible, watcher=False)
        self.host.attach_journal(journal.append, deferred=journal.waits)
        self.schemas.on_added = journal.append_schemas
        # Task entries of the previous run: every session ended with it, so its tasks did too. Delete
        # them as the task manager would, so watchers see a DELETE, not an entry that silently vanished.
        for sa, state in stored.wms.items():
            if sa not in hosted:
                continue
            author = Identity(f"{sa}.task_manager", sa, True)
            for record in state.entries:
                if record.type == TASK_TYPE:
                    self.host.system_write(author, BatchOp(Operation.DELETE, sa, record.id))
        self.durable_sync()  # serve nobody before those deletes are visible

    @property
    def durable_at_once(self) -> bool:
        """Whether every applied write is durable at once (no journal that writers wait for)."""
        journal = self.journal
        return journal is None or not journal.waits

    async def durable(self) -> None:
        """Return once every write made so far is durable (and visible), at once without a waiting journal.

        Every call that writes or checks the latest state (writes and their
        refusals, locks, task calls) answers only after this, so that what it
        tells its caller can no longer be undone by a crash (cast.core.access).
        """
        journal = self.journal
        if journal is not None and journal.waits:
            await journal.wait_async(journal.ticket())

    def durable_sync(self) -> None:
        """:meth:`durable` for callers on their own threads (in-process components)."""
        journal = self.journal
        if journal is not None and journal.waits:
            journal.wait(journal.ticket())

    def close(self) -> None:
        """Flush and close the journal (a clean shutdown); the System must not be written after."""
        if self.journal is not None:
            self.schemas.on_added = None
            self.journal.close()  # applies what it writes on the way
            self.host.detach_journal()
        if self.shared is not None:
            self.shared.close()

    def expect(self, info: ComponentInfo) -> None:
        """Record a configured component so the directory lists it before it connects."""
        self.sessions.expect(info)

    def _session_ended(self, component_id: str) -> None:
        self.host.release_component(component_id)
        self.tasks.release_component(component_id)

    def _publish_task(self, task: TaskRecord) -> int:
        """Write a task's state into its SA's WM; return the revision of the last write."""
        author = Identity(f"{task.subarchitecture}.task_manager", task.subarchitecture, True)
        data = self._encode_task(task) if self._encode_task is not None else b""
        sa, tid = task.subarchitecture, task.task_id
        if task.state is TaskState.WAITING:
            return self.host.system_write(author, BatchOp(Operation.ADD, sa, tid, TASK_TYPE, data)).revision
        result = self.host.system_write(author, BatchOp(Operation.OVERWRITE, sa, tid, TASK_TYPE, data))
        if task.state not in (TaskState.WAITING, TaskState.ADOPTED):
            # Ended tasks leave the WM; their final state is the overwrite just before.
            result = self.host.system_write(author, BatchOp(Operation.DELETE, sa, tid))
        return result.revision
