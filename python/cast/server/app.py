"""Starting and stopping a CAST server: grpc.aio, the three services, health and reflection."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from cast.auth import TokenSigner
from cast.config import SystemConfig
from cast.core.sessions import ComponentInfo
from cast.core.system import System
from cast.server.directory import DirectoryServicer
from cast.server.inspection import InspectionServicer
from cast.server.rpc import Authenticator
from cast.server.task_manager import TaskManagerServicer
from cast.server.working_memory import WorkingMemoryServicer
from cast.v1 import (
    directory_pb2,
    directory_pb2_grpc,
    inspection_pb2,
    inspection_pb2_grpc,
    task_manager_pb2,
    task_manager_pb2_grpc,
    working_memory_pb2,
    working_memory_pb2_grpc,
)

__all__ = ["RunningServer", "serve_forever", "start_server", "system_from_config"]

log = logging.getLogger("cast.server")

MAX_MESSAGE_BYTES = 64 * 1024 * 1024
SERVICE_NAMES = (
    working_memory_pb2.DESCRIPTOR.services_by_name["WorkingMemory"].full_name,
    task_manager_pb2.DESCRIPTOR.services_by_name["TaskManager"].full_name,
    directory_pb2.DESCRIPTOR.services_by_name["Directory"].full_name,
    inspection_pb2.DESCRIPTOR.services_by_name["Inspection"].full_name,
)


def system_from_config(config: SystemConfig, lease_ms: int = 10_000) -> System:
    """A :class:`System` hosting every SA of a configuration, expecting its components."""
    system = System(
        config.name,
        list(config.subarchitectures),
        {name: sa.make_policy() for name, sa in config.subarchitectures.items()},
        config.limits,
        lease_ms=lease_ms,
    )
    for comp in config.components:
        system.expect(ComponentInfo(comp.id, comp.subarchitecture, comp.privileged, comp.language, comp.kind))
    return system


@dataclass
class RunningServer:
    """A started server: its address, and how to stop it."""

    server: grpc.aio.Server
    system: System
    host: str
    port: int
    _tasks: list[asyncio.Task[None]] = field(default_factory=list)
    _on_stop: list[Callable[[], None]] = field(default_factory=list)

    @property
    def endpoint(self) -> str:
        """``host:port`` clients connect to."""
        return f"{self.host}:{self.port}"

    def on_stop(self, callback: Callable[[], None]) -> None:
        """Run ``callback`` (e.g. stopping in-process components) before the server stops."""
        self._on_stop.append(callback)

    async def stop(self, grace: float = 1.0) -> None:
        """Stop in-process components, then the server, letting calls finish for ``grace`` seconds."""
        for callback in reversed(self._on_stop):
            await asyncio.get_running_loop().run_in_executor(None, callback)
        for task in self._tasks:
            task.cancel()
        await self.server.stop(grace)


async def _expire_sessions(system: System) -> None:
    period = max(0.05, system.sessions.lease_ms / 4000)
    while True:
        await asyncio.sleep(period)
        for component_id in system.sessions.expire():
            log.warning("session of component '%s' expired: its locks and tasks were released", component_id)


def _split_listen(listen: str) -> tuple[str, str]:
    host, sep, port = listen.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"listen address '{listen}' must be HOST:PORT (port 0 picks a free port)")
    return host or "0.0.0.0", port


async def start_server(system: System, signer: TokenSigner, listen: str = "127.0.0.1:0") -> RunningServer:
    """Start serving ``system`` on ``listen`` (HOST:PORT; port 0 picks a free one)."""
    host, _ = _split_listen(listen)
    options: Sequence[tuple[str, int]] = (
        ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
        ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
        # Notice dead peers (a crashed component's streams) even on an idle connection.
        ("grpc.keepalive_time_ms", 10_000),
        ("grpc.keepalive_timeout_ms", 5_000),
        ("grpc.http2.min_ping_interval_without_data_ms", 5_000),
        ("grpc.keepalive_permit_without_calls", 1),
    )
    server = grpc.aio.server(options=options)
    auth = Authenticator(signer)
    working_memory_pb2_grpc.add_WorkingMemoryServicer_to_server(WorkingMemoryServicer(system, auth), server)
    task_manager_pb2_grpc.add_TaskManagerServicer_to_server(TaskManagerServicer(system, auth), server)
    directory_pb2_grpc.add_DirectoryServicer_to_server(DirectoryServicer(system, auth), server)
    inspection_pb2_grpc.add_InspectionServicer_to_server(InspectionServicer(system, auth), server)
    health_servicer = health.aio.HealthServicer()  # type: ignore[attr-defined]
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(
        (*SERVICE_NAMES, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME),
        server,
    )
    port = server.add_insecure_port(listen)
    if port == 0:
        raise OSError(f"cannot listen on {listen}: address in use or not available")
    await server.start()
    advertised = "127.0.0.1" if host in ("0.0.0.0", "[::]", "::") else host
    for sa in system.endpoints:
        system.endpoints[sa] = f"{advertised}:{port}"
    for name in ("", *SERVICE_NAMES):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    running = RunningServer(server, system, advertised, port)
    running._tasks.append(asyncio.ensure_future(_expire_sessions(system)))
    return running


async def serve_forever(
    system: System,
    signer: TokenSigner,
    listen: str,
    on_started: Callable[[RunningServer], None] | None = None,
) -> None:
    """Serve until SIGINT or SIGTERM, printing ``listening on HOST:PORT`` first."""
    running = await start_server(system, signer, listen)
    print(f"listening on {running.endpoint}", flush=True)
    if on_started is not None:
        on_started(running)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    print("stopping", file=sys.stderr, flush=True)
    await running.stop()
