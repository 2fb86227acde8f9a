"""The servers of a system, run inside the orchestrator's event loop.

Each ``servers:`` entry of the configuration becomes one gRPC server (one
:class:`System`) on its own port; the first one is the directory that
components are given as ``CAST_ENDPOINT``. Every server knows where the SAs of
the others are served, so a component reaches any SA through the directory.
In-process components run inside the server hosting their SA.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import grpc
import grpc.aio

from cast.auth import TokenSigner
from cast.config.model import LOCAL_HOST, ComponentConfig, ServerConfig, SystemConfig
from cast.core.system import System
from cast.errors import InvalidArgumentError
from cast.orchestrator.agent_link import orchestrator_metadata
from cast.orchestrator.process import LineSink
from cast.orchestrator.remote import Agents, RemoteProcess
from cast.orchestrator.security import component_tls
from cast.server.app import RunningServer, settings_from_config, start_server, system_from_config
from cast.server.in_process import InProcessComponents
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc

__all__ = ["HostedServer", "RemoteServer", "ServerGroup", "build_system"]


def build_system(config: SystemConfig, server: ServerConfig) -> System:
    """The :class:`System` of one server: its SAs with their policies, expecting every component."""
    # The server's persistence, TLS and token rules come with it (cast.server.app.system_from_config).
    return system_from_config(config, config.orchestrator.lease_ms, server)


@dataclass
class HostedServer:
    """One started server."""

    config: ServerConfig
    system: System
    running: RunningServer
    in_process: InProcessComponents = field(init=False)

    def __post_init__(self) -> None:
        self.in_process = InProcessComponents(self.system)
        self.running.on_stop(self.in_process.stop_all)

    @property
    def endpoint(self) -> str:
        """``host:port`` of the server."""
        return self.running.endpoint


@dataclass
class RemoteServer:
    """A server on another host: ``cast serve`` started by its agent (docs/multihost.md)."""

    config: ServerConfig
    process: RemoteProcess

    @property
    def endpoint(self) -> str:
        """``host:port`` the server reported (its first line)."""
        return self.process.endpoint

    @property
    def address(self) -> str:
        """What the other hosts dial."""
        return self.config.address(self.endpoint)


class ServerGroup:
    """Every server of a system: in this process (:attr:`servers`), and on other hosts (:attr:`remote`)."""

    def __init__(self, config: SystemConfig, signer: TokenSigner) -> None:
        self.config = config
        self.signer = signer
        self.servers: list[HostedServer] = []
        self.remote: list[RemoteServer] = []

    async def start(self) -> None:
        """Start every server of this host, then tell each where the others' SAs are."""
        if self.config.servers and self.config.servers[0].host != LOCAL_HOST:
            raise InvalidArgumentError(
                f"server '{self.config.servers[0].name}' is the directory (the first server) and runs on host "
                f"'{self.config.servers[0].host}': the directory runs on the orchestrator's host for now; put a "
                "server without host: first (docs/multihost.md)")
        try:
            for server_config in self.config.servers:
                if server_config.host != LOCAL_HOST:
                    continue  # started through its agent (start_remote)
                system = build_system(self.config, server_config)
                system.barrier.hold()  # run() waits until every component has started (release_run)
                running = await start_server(
                    system, self.signer, server_config.listen, settings_from_config(self.config)
                )
                self.servers.append(HostedServer(server_config, system, running))
        except BaseException:
            await self.stop()
            raise
        for server in self.servers:
            for other in self.servers:
                if other is not server:
                    for sa in other.config.subarchitectures:
                        # What other hosts dial (advertise:), since components there follow these routes too.
                        server.running.routes.remote[sa] = other.config.address(other.endpoint)

    async def start_remote(self, agents: Agents, logs: Path, sink: LineSink) -> None:
        """Start the servers of other hosts through their agents (after :meth:`start`), in the file's order.

        Each is given the routes to every other server's SAs: the servers of this host and those started
        before it by their bound addresses, those started after it by their configured address, which
        therefore needs a fixed port. Each holds its start barrier until the directory's is released.
        """
        remote = [s for s in self.config.servers if s.host != LOCAL_HOST]
        directory = self.directory
        for server_config in remote:
            routes: dict[str, str] = {}
            for other in self.config.servers:
                if other is server_config:
                    continue
                address = self._address_of(other)
                if address is None:
                    raise InvalidArgumentError(
                        f"server '{server_config.name}' on host '{server_config.host}' must know where server "
                        f"'{other.name}' is before that one starts: give '{other.name}' a fixed port in listen: "
                        "or advertise: (docs/multihost.md)")
                routes.update({sa: address for sa in other.subarchitectures})
            proc = agents.server_process(server_config, routes, directory.config.address(directory.endpoint),
                                         logs / f"server-{server_config.name}.log", sink)
            await proc.start()
            self.remote.append(RemoteServer(server_config, proc))
        for server in self.servers:
            for far in self.remote:
                for sa in far.config.subarchitectures:
                    server.running.routes.remote[sa] = far.address

    def _address_of(self, server: ServerConfig) -> str | None:
        """Where the other hosts reach ``server``: bound and advertised, or configured with a fixed port."""
        for hosted in self.servers:
            if hosted.config is server:
                return server.address(hosted.endpoint)
        for far in self.remote:
            if far.config is server:
                return far.address
        configured = server.advertise or server.listen
        host, _, port = configured.rpartition(":")
        if port == "0" or host in ("0.0.0.0", "[::]", "::", ""):
            return None
        return configured

    def remote_channel(self, far: RemoteServer) -> grpc.aio.Channel:
        """A channel to a server on another host, with the components' TLS files in a TLS system."""
        tls = component_tls(self.config)
        if tls is not None:
            return grpc.aio.secure_channel(far.address, tls.credentials(), options=tls.channel_options())
        return grpc.aio.insecure_channel(far.address)

    def orchestrator_metadata(self) -> tuple[tuple[str, str], ...]:
        """The privileged token the orchestrator's own calls to a server carry (the one agents get too)."""
        return orchestrator_metadata(self.signer)

    async def remote_components(self) -> list[dir_pb2.ComponentInfo]:
        """The components each server on another host knows (Directory.DescribeSystem); none if unreachable."""
        found: list[dir_pb2.ComponentInfo] = []
        for far in self.remote:
            if not far.process.running:
                continue
            async with self.remote_channel(far) as channel:
                try:
                    reply = await directory_pb2_grpc.DirectoryStub(channel).DescribeSystem(
                        dir_pb2.DescribeSystemRequest(), metadata=self.orchestrator_metadata(), timeout=2.0)
                except grpc.RpcError:
                    continue
            found.extend(reply.components)
        return found

    async def stop_remote(self, timeout: float) -> None:
        """Stop the servers on other hosts (Agent.Stop: SIGTERM, SIGKILL after ``timeout``), last first."""
        for far in reversed(self.remote):
            await far.process.stop(timeout)
        self.remote.clear()

    def release_run(self) -> None:
        """Release the start barrier of every server: each component's run() may begin."""
        for server in self.servers:
            server.system.barrier.release()

    @property
    def directory(self) -> HostedServer:
        """The first server: components are given its address."""
        return self.servers[0]

    def hosting(self, sa: str) -> HostedServer:
        """The server hosting an SA."""
        return next(s for s in self.servers if sa in s.config.subarchitectures)

    def start_in_process(self, component: ComponentConfig) -> None:
        """Start an in-process component inside the server hosting its SA (one on another host starts its own)."""
        if any(component.subarchitecture in far.config.subarchitectures for far in self.remote):
            return
        self.hosting(component.subarchitecture).in_process.start(component)

    def stop_in_process(self) -> None:
        """Stop every in-process component (reverse start order)."""
        for server in reversed(self.servers):
            server.in_process.stop_all()

    async def stop(self) -> None:
        """Stop every server (in-process components first)."""
        for server in reversed(self.servers):
            await server.running.stop()
        self.servers.clear()
