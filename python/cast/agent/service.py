"""The ``cast.v1.Agent`` servicer: translates the wire messages to the process table and back.

Errors are the project's named errors (:mod:`cast.errors`), each turned into
its status code with its message, which names the thing and what to do.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

import grpc

from cast.agent.launch import load_from_root, plan_launch, plan_server, probe
from cast.agent.processes import ProcessTable
from cast.agent.sessions import SystemSession
from cast.errors import CastError, InvalidArgumentError, UnavailableError
from cast.v1 import agent_pb2, agent_pb2_grpc

__all__ = ["AgentServicer"]

T = TypeVar("T")
Context = grpc.aio.ServicerContext[Any, Any]

DEFAULT_STOP_TIMEOUT_MS = 10_000
SERVER_START_TIMEOUT_S = 30.0


async def _answer(context: Context, work: Callable[[], Awaitable[T]]) -> T:
    """``work()``'s result; a CastError becomes its status code and message."""
    try:
        return await work()
    except CastError as exc:
        await context.abort(grpc.StatusCode[exc.code], exc.message)
        raise  # abort raises; this keeps type checkers sure nothing returns here


class AgentServicer(agent_pb2_grpc.AgentServicer):
    """Attach, Launch, Stop, Renew and Probe over one :class:`ProcessTable`."""

    def __init__(self, table: ProcessTable, secret_file: Path | None = None) -> None:
        self.table = table
        # Given to the servers it starts: they verify component tokens with it.
        self.secret_file = secret_file.resolve() if secret_file else None
        self.host = socket.gethostname()

    @property
    def root(self) -> Path:
        """The agent's --root."""
        return self.table.root

    async def Attach(
        self, request_iterator: AsyncIterator[agent_pb2.AttachRequest], context: Context
    ) -> AsyncIterator[agent_pb2.AgentEvent]:
        """The session stream: the attached event, then every unacknowledged event as it comes."""
        first = await anext(aiter(request_iterator), None)
        if first is None:
            return
        if not first.system:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "the first AttachRequest must name the system")
        session, resumed = self.table.open_session(first.system, first.lease_ms, first.grace_ms)
        # A new session numbers its events from 1: an ack of the caller's last session (this agent was
        # restarted, or the old session ended) says nothing about them, and would withhold them.
        start = first.ack_seq if resumed else 0
        session.ack(start)
        stream = session.attach()
        reader = asyncio.ensure_future(self._keepalives(request_iterator, session, stream))
        try:
            yield agent_pb2.AgentEvent(attached=agent_pb2.AgentAttached(
                host=self.host, root=str(self.root), agent_pid=os.getpid(),
                running=self.table.running(first.system), resumed=resumed))
            seq = start
            while True:
                events = await session.wait(stream, seq)
                if events is None:
                    break
                for event in events:
                    yield event
                    seq = event.seq
            if session.ended:
                await context.abort(grpc.StatusCode.ABORTED,
                                    f"the session of system '{first.system}' ended (its lease ran out or the "
                                    "agent is stopping): its processes were stopped")
            if session.attached:
                await context.abort(grpc.StatusCode.ABORTED,
                                    f"another Attach for system '{first.system}' took this session over")
            # Otherwise the orchestrator closed its side: the lease counts from now.
        finally:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await reader
            session.detach(stream)

    async def _keepalives(
        self, requests: AsyncIterator[agent_pb2.AttachRequest], session: SystemSession, stream: int
    ) -> None:
        """Each request renews the lease and acknowledges events; the end of the requests detaches."""
        with contextlib.suppress(grpc.RpcError, asyncio.CancelledError):
            async for request in requests:
                if session.stream != stream:
                    return
                session.touch()
                session.ack(request.ack_seq)
        session.detach(stream)

    async def Launch(self, request: agent_pb2.LaunchRequest, context: Context) -> agent_pb2.LaunchResponse:
        """Start one component process; nothing is started on any error."""
        async def work() -> agent_pb2.LaunchResponse:
            self.table.session(request.system)  # fail before anything is read when there is no session
            config = load_from_root(self.root, request.config_path, request.sets)
            if request.server:
                return await self._launch_server(request, config)
            plan = plan_launch(config, request.component_id, request.env, token_file=request.token_file)
            try:
                proc = await self.table.launch(request.system, plan)
            except OSError as exc:
                raise InvalidArgumentError(f"component '{request.component_id}': cannot start {plan.argv[0]}: "
                                           f"{exc.strerror or exc}") from exc
            return agent_pb2.LaunchResponse(pid=proc.process.pid, argv=plan.argv, log_path=str(proc.process.log_path))

        return await _answer(context, work)

    async def _launch_server(self, request: agent_pb2.LaunchRequest, config: Any) -> agent_pb2.LaunchResponse:
        """``cast serve`` for one server; the reply waits for its ``listening on HOST:PORT`` line."""
        if request.env:
            raise InvalidArgumentError(f"server '{request.server}': a server takes no launch environment")
        plan = plan_server(config, (self.root / request.config_path).resolve(), request.server, request.routes,
                           request.await_run, self.secret_file, request.sets)
        first: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        try:
            proc = await self.table.launch(request.system, plan, first)
        except OSError as exc:
            raise InvalidArgumentError(f"server '{request.server}': cannot start {plan.argv[0]}: "
                                       f"{exc.strerror or exc}") from exc
        exited: asyncio.Future[Any] = asyncio.ensure_future(proc.process.wait())
        try:
            await asyncio.wait([first, exited], timeout=SERVER_START_TIMEOUT_S, return_when=asyncio.FIRST_COMPLETED)
        finally:
            exited.cancel()
        line = first.result() if first.done() else ""
        if not line.startswith("listening on "):
            await self.table.stop(request.system, plan.process_id, 1.0, "stopped")
            raise UnavailableError(f"server '{request.server}' did not start on this host: "
                                   + (f"it printed {line!r}" if line else "no output") + f" (its log: "
                                   f"{proc.process.log_path})")
        return agent_pb2.LaunchResponse(pid=proc.process.pid, argv=plan.argv, log_path=str(proc.process.log_path),
                                        endpoint=line.removeprefix("listening on ").strip())

    async def Stop(self, request: agent_pb2.StopRequest, context: Context) -> agent_pb2.StopResponse:
        """SIGTERM, then SIGKILL after the timeout; the exit."""
        async def work() -> agent_pb2.StopResponse:
            timeout = (request.timeout_ms or DEFAULT_STOP_TIMEOUT_MS) / 1000
            exit_ = await self.table.stop(request.system, request.component_id, timeout, "stopped")
            return agent_pb2.StopResponse(exit=exit_)

        return await _answer(context, work)

    async def Renew(self, request: agent_pb2.RenewRequest, context: Context) -> agent_pb2.RenewResponse:
        """Rewrite the token file of a component launched with token_file."""
        async def work() -> agent_pb2.RenewResponse:
            if not request.token:
                raise InvalidArgumentError(f"component '{request.component_id}': Renew needs the new token")
            self.table.renew(request.system, request.component_id, request.token)
            return agent_pb2.RenewResponse()

        return await _answer(context, work)

    async def Probe(self, request: agent_pb2.ProbeRequest, context: Context) -> agent_pb2.ProbeResponse:
        """Whether each component could be launched here."""
        async def work() -> agent_pb2.ProbeResponse:
            config = load_from_root(self.root, request.config_path, request.sets)
            results = [agent_pb2.ProbeResult(component_id=cid, launchable=problem is None, problem=problem or "")
                       for cid, problem in probe(config, list(request.component_ids), self.secret_file)]
            return agent_pb2.ProbeResponse(results=results, host=self.host, root=str(self.root))

        return await _answer(context, work)
