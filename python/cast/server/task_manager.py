"""The TaskManager servicer: proposals, retractions, completions, decision streams."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator

from cast.convert import any_to_type_data, task_to_pb
from cast.core.system import System
from cast.core.tasks import TaskOutcome
from cast.errors import InvalidArgumentError
from cast.server.rpc import Authenticator, Context, rpc, stream_rpc
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.v1 import task_manager_pb2_grpc as tm_grpc

__all__ = ["TaskManagerServicer"]


class TaskManagerServicer(tm_grpc.TaskManagerServicer):
    """Serves the task managers of one :class:`System`."""

    def __init__(self, system: System, auth: Authenticator) -> None:
        self._tasks = system.tasks
        self._auth = auth
        self._system = system

    @rpc
    async def Propose(
        self, request: tm_pb2.ProposeRequest, context: Context
    ) -> tm_pb2.ProposeResponse:
        """Propose a task to the caller's SA."""
        who = self._auth.identify(context)
        data_type, data = any_to_type_data(request.data, "task data") if request.HasField("data") else ("", b"")
        name, priority = request.name, request.priority
        task = await self._system.settle(lambda: self._tasks.propose(who, name, data_type, data, priority))
        return tm_pb2.ProposeResponse(task=task_to_pb(task))

    @rpc
    async def Retract(
        self, request: tm_pb2.RetractRequest, context: Context
    ) -> tm_pb2.RetractResponse:
        """Withdraw a task."""
        who = self._auth.identify(context)
        await self._system.settle(lambda: self._tasks.retract(who, request.task_id))
        return tm_pb2.RetractResponse()

    @rpc
    async def Complete(
        self, request: tm_pb2.CompleteRequest, context: Context
    ) -> tm_pb2.CompleteResponse:
        """Report the outcome of an adopted task."""
        who = self._auth.identify(context)
        try:
            outcome = TaskOutcome(request.outcome)
        except ValueError:
            raise InvalidArgumentError(f"unknown task outcome {request.outcome}") from None
        if outcome is TaskOutcome.UNSPECIFIED:
            raise InvalidArgumentError("a completed task needs an outcome: SUCCEEDED, FAILED or ABANDONED")
        await self._system.settle(lambda: self._tasks.complete(who, request.task_id, outcome, request.reason))
        return tm_pb2.CompleteResponse()

    @rpc
    async def ListTasks(
        self, request: tm_pb2.ListTasksRequest, context: Context
    ) -> tm_pb2.ListTasksResponse:
        """The live tasks of one SA or all."""
        self._auth.identify_read(context)
        tasks = [task_to_pb(t) for t in self._tasks.tasks(request.subarchitecture)]
        await self._system.durable()  # the task states listed are durable before anyone sees them
        return tm_pb2.ListTasksResponse(tasks=tasks)

    @stream_rpc
    async def Decisions(
        self, request: tm_pb2.DecisionsRequest, context: Context
    ) -> AsyncIterator[tm_pb2.Task]:
        """Stream the decisions about the caller's tasks."""
        who = self._auth.identify(context)
        loop = asyncio.get_running_loop()
        loop_thread = threading.get_ident()
        wake = asyncio.Event()

        def listener(component_id: str) -> None:
            if component_id != who.component_id:
                return
            if threading.get_ident() == loop_thread:
                wake.set()
            else:
                loop.call_soon_threadsafe(wake.set)

        self._tasks.add_listener(listener)
        try:
            while True:
                for task in self._tasks.take_decisions(who.component_id):
                    yield task_to_pb(task)
                await wake.wait()
                wake.clear()
        finally:
            self._tasks.remove_listener(listener)
