"""Starting and stopping an agent: grpc.aio with the Agent service, health, reflection and the trust check."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from cast.agent.processes import ProcessTable
from cast.agent.service import AgentServicer
from cast.agent.trust import AgentTrust, TrustInterceptor
from cast.errors import InvalidArgumentError
from cast.signals import say, termination
from cast.v1 import agent_pb2, agent_pb2_grpc

__all__ = ["AGENT_SERVICE", "RunningAgent", "serve_agent", "start_agent"]

AGENT_SERVICE = agent_pb2.DESCRIPTOR.services_by_name["Agent"].full_name
_HEALTH_SERVICE = health_pb2.DESCRIPTOR.services_by_name["Health"].full_name

_OPTIONS = (
    # Notice a dead orchestrator's connection even while idle, so its Attach stream ends.
    ("grpc.keepalive_time_ms", 10_000),
    ("grpc.keepalive_timeout_ms", 5_000),
    ("grpc.http2.min_ping_interval_without_data_ms", 5_000),
    ("grpc.keepalive_permit_without_calls", 1),
)


@dataclass
class RunningAgent:
    """A started agent: where it listens, its process table, how to stop it."""

    server: grpc.aio.Server
    table: ProcessTable
    endpoint: str
    _tasks: list[asyncio.Task[None]] = field(default_factory=list)

    async def stop(self, grace: float = 1.0) -> None:
        """Stop every process it started (SIGTERM, then SIGKILL), then the server."""
        try:
            await self.table.stop_everything("agent stopping")
        finally:
            self.table.kill_everything()
            for task in self._tasks:
                task.cancel()
            await self.server.stop(grace)


def _check_listen(listen: str) -> None:
    host, sep, port = listen.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise InvalidArgumentError(f"--listen '{listen}' must be HOST:PORT (port 0 picks a free one); the agent "
                                   "listens on that address only")


async def start_agent(listen: str, root: Path, trust: AgentTrust, log_dir: Path | None = None) -> RunningAgent:
    """Serve the Agent service on ``listen`` (HOST:PORT) for processes under ``root``."""
    _check_listen(listen)
    if not root.is_dir():
        raise InvalidArgumentError(f"--root {root} is not a directory: give the checkout or install that holds "
                                   "the configurations and components (the same as the orchestrator's)")
    root = root.resolve()
    table = ProcessTable(root, (log_dir or root / ".cast" / "agent" / "logs").resolve())
    server = grpc.aio.server(options=_OPTIONS, interceptors=[TrustInterceptor(trust)])
    agent_pb2_grpc.add_AgentServicer_to_server(AgentServicer(table, trust.secret_file), server)
    health_servicer = health.aio.HealthServicer()  # type: ignore[attr-defined]
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection((AGENT_SERVICE, _HEALTH_SERVICE, reflection.SERVICE_NAME), server)
    credentials = trust.credentials()
    port = server.add_secure_port(listen, credentials) if credentials else server.add_insecure_port(listen)
    if port == 0:
        raise OSError(f"cannot listen on {listen}: address in use or not available")
    await server.start()
    for name in ("", AGENT_SERVICE):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    host = listen.rpartition(":")[0]
    running = RunningAgent(server, table, f"{host}:{port}")
    running._tasks += [asyncio.ensure_future(table.reap_forever()), asyncio.ensure_future(table.sample_forever())]
    return running


async def serve_agent(
    listen: str, root: Path, trust: AgentTrust, log_dir: Path | None = None,
    on_started: Callable[[RunningAgent], None] | None = None,
) -> None:
    """Serve until SIGINT, SIGTERM or SIGHUP; the first line printed says where it listens and whom it trusts."""
    terminated = termination()
    running = await start_agent(listen, root, trust, log_dir)
    say(f"cast agent listening on {running.endpoint} (root {running.table.root}; trusts {trust.describe()})")
    if on_started is not None:
        on_started(running)
    await terminated.wait()
    say("cast agent stopping: stopping every process it started", sys.stderr)
    await running.stop()
