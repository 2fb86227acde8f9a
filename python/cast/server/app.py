"""Starting and stopping a CAST server: grpc.aio, the three services, health and reflection."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import resource
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from cast.auth import TokenSigner
from cast.config import ServerConfig, SystemConfig, TlsConfig
from cast.core.journal import Journal
from cast.core.sessions import ComponentInfo
from cast.core.system import System
from cast.server.directory import DirectoryServicer
from cast.server.inspection import InspectionServicer
from cast.server.malformed import SafeRegistrar
from cast.server.reflection import add_reflection
from cast.server.routes import Routes
from cast.server.rpc import Authenticator
from cast.server.shared_socket import SharedSocket
from cast.server.task_manager import TaskManagerServicer
from cast.server.wire import wire_system
from cast.server.working_memory import WorkingMemoryServicer
from cast.server.working_memory import add_to_server as add_working_memory
from cast.signals import say, termination
from cast.v1 import (
    directory_pb2,
    directory_pb2_grpc,
    inspection_pb2,
    inspection_pb2_grpc,
    task_manager_pb2,
    task_manager_pb2_grpc,
    working_memory_pb2,
)

__all__ = [
    "RunningServer",
    "ServerSettings",
    "serve_forever",
    "settings_from_config",
    "server_credentials",
    "start_server",
    "system_from_config",
]

log = logging.getLogger("cast.server")

MAX_MESSAGE_BYTES = 64 * 1024 * 1024
SERVICE_NAMES = (
    working_memory_pb2.DESCRIPTOR.services_by_name["WorkingMemory"].full_name,
    task_manager_pb2.DESCRIPTOR.services_by_name["TaskManager"].full_name,
    directory_pb2.DESCRIPTOR.services_by_name["Directory"].full_name,
    inspection_pb2.DESCRIPTOR.services_by_name["Inspection"].full_name,
)


@dataclass(frozen=True)
class ServerSettings:
    """How a server is reached and whom it answers: TLS files, and whether reads need a token."""

    tls: TlsConfig | None = None
    reads_require_token: bool = True


def settings_from_config(config: SystemConfig) -> ServerSettings:
    """The TLS files and token rules of the configuration's servers."""
    return ServerSettings(config.tls, config.auth.reads_require_token)


def system_from_config(
    config: SystemConfig,
    lease_ms: int = 10_000,
    server: ServerConfig | None = None,
    metrics: bool = True,
    shared_memory: bool = True,
) -> System:
    """A :class:`System` hosting the SAs of ``server`` (default: every SA), expecting every component.

    The server's ``persistence`` opens its journal and restores what it holds;
    without ``server`` the single configured server's persistence is used (a
    configuration with several servers run as one by ``cast serve`` keeps
    memory only). TLS and token rules are the server's
    (:func:`settings_from_config`), given to :func:`start_server`.
    ``metrics``: whether the server counts what callers do (cast.core.metrics).
    ``shared_memory``: False turns shared memory off whatever the configuration
    says (``cast serve --no-shared-memory``).
    """
    if server is None:
        hosted = list(config.subarchitectures)
        persistence = config.servers[0].persistence if len(config.servers) == 1 else None
    else:
        hosted, persistence = list(server.subarchitectures), server.persistence
    journal = None
    if persistence is not None:
        journal = Journal(persistence.path, persistence.durability, config.limits.history_events)
    system = wire_system(
        config.name,
        hosted,
        policies={name: config.subarchitectures[name].make_policy() for name in hosted},
        limits=config.limits,
        lease_ms=lease_ms,
        journal=journal,
        quotas={comp.id: comp.quota for comp in config.components if comp.quota is not None},
        metrics=metrics,
        shared_memory=config.shared_memory if shared_memory else None,
    )
    for comp in config.components:
        # With hosts: a component shows the host the configuration places it on (local or a hosts: name).
        placed = comp.host if config.hosts else ""
        system.expect(ComponentInfo(comp.id, comp.subarchitecture, comp.privileged, comp.language, comp.kind,
                                    host=placed, placed_on=placed))
    return system


def server_credentials(tls: TlsConfig) -> grpc.ServerCredentials:
    """Credentials of a TLS server: its certificate, and the CA that client certificates must chain to."""
    try:
        key, cert, ca = tls.key.read_bytes(), tls.cert.read_bytes(), tls.ca.read_bytes()
    except OSError as exc:
        raise OSError(f"cannot read the TLS files of the configuration (tls.ca/cert/key): {exc}") from exc
    return grpc.ssl_server_credentials(
        [(key, cert)], root_certificates=ca if tls.client_auth else None, require_client_auth=tls.client_auth
    )


@dataclass
class RunningServer:
    """A started server: its address, and how to stop it."""

    server: grpc.aio.Server
    system: System
    host: str
    port: int
    routes: Routes
    shared: SharedSocket | None = None  # the shared-memory socket, when the system keeps shared memory
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
        """Stop in-process components, then the server, letting calls finish for ``grace`` seconds.

        Last, the journal is flushed and closed (a clean shutdown loses nothing in any mode).
        """
        for callback in reversed(self._on_stop):
            await asyncio.get_running_loop().run_in_executor(None, callback)
        for task in self._tasks:
            task.cancel()
        await self.server.stop(grace)
        if self.shared is not None:
            self.shared.close()
        await asyncio.get_running_loop().run_in_executor(None, self.system.close)


async def _expire_sessions(system: System) -> None:
    period = max(0.05, system.sessions.lease_ms / 4000)
    while True:
        await asyncio.sleep(period)
        for component_id in system.sessions.expire():
            log.warning("session of component '%s' expired: its locks and tasks were released", component_id)


def raise_open_files_limit() -> None:
    """Raise this process's limit of open files to what the system allows it.

    Each client holds a connection, and one on the host a shared-memory
    session too: the usual soft limit of 1,024 would refuse the 500th
    component; the hard limit is the system's bound, as Go's runtime does.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def _split_listen(listen: str) -> tuple[str, str]:
    host, sep, port = listen.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"listen address '{listen}' must be HOST:PORT (port 0 picks a free port)")
    return host or "0.0.0.0", port


async def start_server(
    system: System, signer: TokenSigner, listen: str = "127.0.0.1:0", settings: ServerSettings | None = None
) -> RunningServer:
    """Start serving ``system`` on ``listen`` (HOST:PORT; port 0 picks a free one).

    ``settings`` (:func:`settings_from_config`) default to plaintext with
    tokens required for every call. With TLS only a TLS port is opened: a
    plaintext client fails its handshake.
    """
    if settings is None:
        settings = ServerSettings()
    routes = Routes.of(system.host.subarchitectures)
    host, _ = _split_listen(listen)
    options: Sequence[tuple[str, int]] = (
        ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
        ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
        # Notice dead peers (a crashed component's streams) even on an idle connection.
        ("grpc.keepalive_time_ms", 10_000),
        ("grpc.keepalive_timeout_ms", 5_000),
        ("grpc.http2.ping_timeout_ms", 5_000),  # what decides it since gRPC 1.5x (cast.client.channel)
        ("grpc.http2.min_ping_interval_without_data_ms", 5_000),
        ("grpc.keepalive_permit_without_calls", 1),
    )
    server = grpc.aio.server(options=options)
    auth = Authenticator(signer, reads_require_token=settings.reads_require_token)
    raise_open_files_limit()
    shared = SharedSocket(system, auth) if system.shared is not None else None
    # Requests whose bytes do not parse are answered INVALID_ARGUMENT (cast.server.malformed).
    registrar: Any = SafeRegistrar(server)
    add_working_memory(WorkingMemoryServicer(system, auth), registrar)
    task_manager_pb2_grpc.add_TaskManagerServicer_to_server(TaskManagerServicer(system, auth), registrar)
    directory = DirectoryServicer(system, auth, routes, shared.info() if shared is not None else None)
    directory_pb2_grpc.add_DirectoryServicer_to_server(directory, registrar)
    inspection_pb2_grpc.add_InspectionServicer_to_server(InspectionServicer(system, auth), registrar)
    health_servicer = health.aio.HealthServicer()  # type: ignore[attr-defined]
    foreign: Any = SafeRegistrar(server, wrap=False)  # generic handlers only, deserializers untouched
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, foreign)
    health_name = health_pb2.DESCRIPTOR.services_by_name["Health"].full_name
    add_reflection(foreign, system.schemas, (*SERVICE_NAMES, health_name))
    if settings.tls is not None:
        port = server.add_secure_port(listen, server_credentials(settings.tls))
    else:
        port = server.add_insecure_port(listen)
    if port == 0:
        if shared is not None:
            shared.close()
        raise OSError(f"cannot listen on {listen}: address in use or not available")
    await server.start()
    advertised = "127.0.0.1" if host in ("0.0.0.0", "[::]", "::") else host
    routes.listening(f"{advertised}:{port}")
    for name in ("", *SERVICE_NAMES):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    running = RunningServer(server, system, advertised, port, routes, shared)
    running._tasks.append(asyncio.ensure_future(_expire_sessions(system)))
    return running


async def serve_forever(
    system: System,
    signer: TokenSigner,
    listen: str,
    on_started: Callable[[RunningServer], None] | None = None,
    settings: ServerSettings | None = None,
) -> None:
    """Serve until SIGINT, SIGTERM or SIGHUP, printing ``listening on HOST:PORT`` first."""
    terminated = termination()
    running = await start_server(system, signer, listen, settings)
    say(f"listening on {running.endpoint}")
    if on_started is not None:
        on_started(running)
    await terminated.wait()
    say("stopping", sys.stderr)
    await running.stop()
