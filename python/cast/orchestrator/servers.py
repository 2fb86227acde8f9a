"""The servers of a system, run inside the orchestrator's event loop.

Each ``servers:`` entry of the configuration becomes one gRPC server (one
:class:`System`) on its own port; the first one is the directory that
components are given as ``CAST_ENDPOINT``. Every server knows where the SAs of
the others are served, so a component reaches any SA through the directory.
In-process components run inside the server hosting their SA.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from cast.auth import TokenSigner
from cast.config.model import ComponentConfig, ServerConfig, SystemConfig
from cast.core.system import System
from cast.server.app import RunningServer, settings_from_config, start_server, system_from_config
from cast.server.in_process import InProcessComponents

__all__ = ["HostedServer", "ServerGroup", "build_system"]


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


class ServerGroup:
    """Every server of a system."""

    def __init__(self, config: SystemConfig, signer: TokenSigner) -> None:
        self.config = config
        self.signer = signer
        self.servers: list[HostedServer] = []

    async def start(self) -> None:
        """Start every server, then tell each where the others' SAs are."""
        try:
            for server_config in self.config.servers:
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
        """Start an in-process component inside the server hosting its SA."""
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
