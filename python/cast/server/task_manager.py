"""The TaskManager servicer: proposals, retractions, completions, decision streams."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator

from cast.core.access import Access, run_async
from cast.core.records import Identity
from cast.core.system import System
from cast.server.conversions import task_to_pb
from cast.server.rpc import Authenticator, Context, Servicer, rpc, stream_rpc
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.v1 import task_manager_pb2_grpc as tm_grpc
from cast.wire.values import any_to_type_data

__all__ = ["TaskManagerServicer"]


class TaskManagerServicer(Servicer, tm_grpc.TaskManagerServicer):
    """Serves the task managers of one :class:`System`: translates requests to the caller's :class:`Access`."""

    SERVICE = "cast.v1.TaskManager"

    def __init__(self, system: System, auth: Authenticator) -> None:
        self.auth = auth
        self._system = system

    @rpc
    async def Propose(
        self, request: tm_pb2.ProposeRequest, context: Context, who: Identity
    ) -> tm_pb2.ProposeResponse:
        """Propose a task to the caller's SA."""
        access = Access(self._system, who)
        data_type, data = any_to_type_data(request.data, "task data") if request.HasField("data") else ("", b"")
        task = await run_async(self._system, access.propose(request.name, data_type, data, request.priority))
        return tm_pb2.ProposeResponse(task=task_to_pb(task))

    @rpc
    async def Retract(
        self, request: tm_pb2.RetractRequest, context: Context, who: Identity
    ) -> tm_pb2.RetractResponse:
        """Withdraw a task."""
        await run_async(self._system, Access(self._system, who).retract(request.task_id))
        return tm_pb2.RetractResponse()

    @rpc
    async def Complete(
        self, request: tm_pb2.CompleteRequest, context: Context, who: Identity
    ) -> tm_pb2.CompleteResponse:
        """Report the outcome of an adopted task."""
        access = Access(self._system, who)
        await run_async(self._system, access.complete(request.task_id, request.outcome, request.reason))
        return tm_pb2.CompleteResponse()

    @rpc
    async def ListTasks(
        self, request: tm_pb2.ListTasksRequest, context: Context, who: Identity
    ) -> tm_pb2.ListTasksResponse:
        """The live tasks of one SA or all."""
        tasks = await run_async(self._system, Access(self._system, who).tasks(request.subarchitecture))
        return tm_pb2.ListTasksResponse(tasks=[task_to_pb(t) for t in tasks])

    @stream_rpc
    async def Decisions(
        self, request: tm_pb2.DecisionsRequest, context: Context, who: Identity
    ) -> AsyncIterator[tm_pb2.Task]:
        """Stream the decisions about the caller's tasks (cast.core.tasks.DecisionFeed)."""
        loop = asyncio.get_running_loop()
        loop_thread = threading.get_ident()
        ready = asyncio.Event()

        def wake() -> None:  # on the thread that decided: in-process components decide on their own
            if threading.get_ident() == loop_thread:
                ready.set()
            else:
                loop.call_soon_threadsafe(ready.set)

        feed = Access(self._system, who).decisions(wake)
        try:
            while True:
                for task in feed.take():
                    yield task_to_pb(task)
                await ready.wait()
                ready.clear()
        finally:
            feed.close()
