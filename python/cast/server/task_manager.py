"""The TaskManager servicer: proposals, retractions, completions, decision streams."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator

from cast.client.conversions import any_to_type_data
from cast.core.access import Access, run_async
from cast.core.system import System
from cast.server.conversions import task_to_pb
from cast.server.rpc import Authenticator, Context, rpc, stream_rpc
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.v1 import task_manager_pb2_grpc as tm_grpc

__all__ = ["TaskManagerServicer"]


class TaskManagerServicer(tm_grpc.TaskManagerServicer):
    """Serves the task managers of one :class:`System`: translates requests to the caller's :class:`Access`."""

    def __init__(self, system: System, auth: Authenticator) -> None:
        self._tasks = system.tasks
        self._auth = auth
        self._system = system

    @rpc
    async def Propose(
        self, request: tm_pb2.ProposeRequest, context: Context
    ) -> tm_pb2.ProposeResponse:
        """Propose a task to the caller's SA."""
        access = Access(self._system, self._auth.identify(context))
        data_type, data = any_to_type_data(request.data, "task data") if request.HasField("data") else ("", b"")
        task = await run_async(self._system, access.propose(request.name, data_type, data, request.priority))
        return tm_pb2.ProposeResponse(task=task_to_pb(task))

    @rpc
    async def Retract(
        self, request: tm_pb2.RetractRequest, context: Context
    ) -> tm_pb2.RetractResponse:
        """Withdraw a task."""
        access = Access(self._system, self._auth.identify(context))
        await run_async(self._system, access.retract(request.task_id))
        return tm_pb2.RetractResponse()

    @rpc
    async def Complete(
        self, request: tm_pb2.CompleteRequest, context: Context
    ) -> tm_pb2.CompleteResponse:
        """Report the outcome of an adopted task."""
        access = Access(self._system, self._auth.identify(context))
        await run_async(self._system, access.complete(request.task_id, request.outcome, request.reason))
        return tm_pb2.CompleteResponse()

    @rpc
    async def ListTasks(
        self, request: tm_pb2.ListTasksRequest, context: Context
    ) -> tm_pb2.ListTasksResponse:
        """The live tasks of one SA or all."""
        access = Access(self._system, self._auth.identify_read(context))
        tasks = await run_async(self._system, access.tasks(request.subarchitecture))
        return tm_pb2.ListTasksResponse(tasks=[task_to_pb(t) for t in tasks])

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
