"""A whole CAST node without the network: WMs, task managers, sessions, schemas.

The server wraps a :class:`System` in gRPC servicers; in-process components
call it directly. Either way the same objects enforce the same guarantees.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence

from cast.core.host import BatchOp, MemoryHost
from cast.core.policies import TaskPolicy
from cast.core.records import Identity, Limits, Operation
from cast.core.schemas import SchemaRegistry, files_of
from cast.core.sessions import ComponentInfo, SessionTable
from cast.core.tasks import TaskBoard, TaskRecord, TaskState

__all__ = ["TASK_TYPE", "System"]

TASK_TYPE = "cast.v1.Task"


class System:
    """Everything one server hosts, wired together."""

    def __init__(
        self,
        name: str,
        subarchitectures: Sequence[str],
        policies: Mapping[str, TaskPolicy] | None = None,
        limits: Limits | None = None,
        lease_ms: int = 10_000,
    ) -> None:
        # Imported here so that importing the core does not require generated code.
        from cast.v1 import task_manager_pb2

        self.name = name
        self.schemas = SchemaRegistry()
        self.schemas.register(files_of(task_manager_pb2.Task.DESCRIPTOR))
        self.host = MemoryHost(subarchitectures, limits, validator=self.schemas.validate)
        self.tasks = TaskBoard(self.host, policies, publish=self._publish_task)
        self.sessions = SessionTable(self._session_ended, lease_ms=lease_ms)
        self.endpoints: dict[str, str] = {sa: "" for sa in subarchitectures}
        # SAs of the same system served by other servers (set by the orchestrator), so that this
        # server's directory routes components to them.
        self.remote_endpoints: dict[str, str] = {}
        self.started_ns = time.time_ns()

    def expect(self, info: ComponentInfo) -> None:
        """Record a configured component so the directory lists it before it connects."""
        self.sessions.expect(info)

    def _session_ended(self, component_id: str) -> None:
        self.host.release_component(component_id)
        self.tasks.release_component(component_id)

    def _publish_task(self, task: TaskRecord) -> None:
        from cast.convert import task_to_pb

        author = Identity(f"{task.subarchitecture}.task_manager", task.subarchitecture, True)
        data = task_to_pb(task).SerializeToString()
        sa, tid = task.subarchitecture, task.task_id
        if task.state is TaskState.WAITING:
            self.host.system_write(author, BatchOp(Operation.ADD, sa, tid, TASK_TYPE, data))
            return
        self.host.system_write(author, BatchOp(Operation.OVERWRITE, sa, tid, TASK_TYPE, data))
        if task.state not in (TaskState.WAITING, TaskState.ADOPTED):
            # Ended tasks leave the WM; their final state is the overwrite just before.
            self.host.system_write(author, BatchOp(Operation.DELETE, sa, tid))
