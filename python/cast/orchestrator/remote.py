"""Components on other hosts: the orchestrator's side of ``cast agent`` (docs/multihost.md).

For each host under ``hosts:`` that runs a component, an
:class:`~cast.orchestrator.agent_link.AgentLink` attaches to that host's agent
with a lease, keeps the session alive and acknowledges its events. A
:class:`RemoteProcess` stands for one component launched there and behaves
like a local :class:`cast.orchestrator.process.ComponentProcess` to the
supervisor: its output lines arrive on the Attach stream and go to the same
log file and terminal sink, its exit arrives as a ``ProcessExit`` event, and
stopping it is ``Agent.Stop`` (SIGTERM, SIGKILL after the timeout, on its host).

The configuration is named relative to the orchestrator's working directory,
which must be the checkout or install each agent has under ``--root``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Mapping
from pathlib import Path

import grpc

from cast.auth import TokenSigner
from cast.config.model import LOCAL_HOST, ComponentConfig, ServerConfig, SystemConfig
from cast.errors import CastError, InvalidArgumentError
from cast.orchestrator.agent_link import AgentLink, agent_channel, describe_failure, orchestrator_metadata
from cast.orchestrator.process import LineSink
from cast.v1 import agent_pb2, agent_pb2_grpc

__all__ = ["SERVER_PREFIX", "Agents", "RemoteProcess", "config_path_for_agents", "probe_hosts", "remote_hosts"]

SERVER_PREFIX = "server:"
"""A server started through an agent is known there as ``server:NAME``."""


def config_path_for_agents(config: SystemConfig, cwd: Path | None = None) -> str:
    """The configuration's path relative to the working directory (every agent's ``--root`` is that checkout)."""
    cwd = (cwd or Path.cwd()).resolve()
    path = Path(config.source).resolve()
    if not path.is_relative_to(cwd):
        raise InvalidArgumentError(
            f"{config.source} is outside the working directory {cwd}: with components on other hosts, run cast "
            "from the root of the checkout that every host's agent has as --root (docs/multihost.md)"
        )
    return path.relative_to(cwd).as_posix()


class RemoteProcess:
    """One component process on another host, as the supervisor sees a process."""

    def __init__(self, link: AgentLink, component_id: str, env: Mapping[str, str], log_path: Path,
                 sink: LineSink) -> None:
        self.link = link
        self.component_id = component_id
        self.env = {k: v for k, v in env.items() if k.startswith("CAST_") and k not in ("CAST_SECRET",
                                                                                       "CAST_SECRET_FILE")}
        self.log_path = log_path
        self._sink = sink
        self.pid = 0
        self.killed = False
        self.dumped = False  # the agent asks for the stacks of one it kills too, but its exit event does not say
        self.host_lost = False  # ended because its host was lost (not an exit the agent reported)
        self._exit: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        self.argv: list[str] = []
        # A server (component_id "server:NAME"): its name, the routes and directory it is given, its endpoint.
        self.server = ""
        self.routes: dict[str, str] = {}
        self.await_run = ""
        self.endpoint = ""

    @property
    def host(self) -> str:
        """The host's name in the configuration."""
        return self.link.host.name

    @property
    def running(self) -> bool:
        """Started and no exit reported yet."""
        return self.pid != 0 and not self._exit.done()

    async def start(self) -> None:
        """Launch through the agent; CastError (with the agent's reason) if it cannot start."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        reply = await self.link.launch(self)
        self.pid, self.argv, self.endpoint = reply.pid, list(reply.argv), reply.endpoint

    def line(self, text: str) -> None:
        """One output line from the agent: to the log file and the sink."""
        with self.log_path.open("a", encoding="utf-8") as log:
            log.write(text + "\n")
        self._sink(self.component_id, text)

    def exited(self, event: agent_pb2.ProcessExit) -> None:
        """The agent reported the end of this process."""
        self.killed = self.killed or event.killed
        if not self._exit.done():
            self._exit.set_result(-event.signal if event.signal else event.exit_code)

    def lost(self, host: bool = False) -> None:
        """No exit will be reported: this process is gone (``host``: with its host, see :meth:`AgentLink.lose`)."""
        if not self._exit.done():
            self.host_lost = host
            self._exit.set_result(-9)

    async def wait(self) -> int:
        """Wait for the exit; the exit code (negative: the signal that ended it)."""
        return await asyncio.shield(self._exit)

    async def stop(self, timeout: float) -> int:
        """``Agent.Stop``: SIGTERM there, SIGKILL after ``timeout`` seconds; the exit code."""
        if self.running:
            try:
                reply = await self.link.stop(self.component_id, timeout)
                self.exited(reply.exit)
            except CastError:
                pass  # ended meanwhile (its exit event is on its way) or the host is lost
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.wait(), 5.0)
            self.lost()
        return await self.wait()

    def kill(self) -> None:
        """Stop at once (a second Ctrl-C): Agent.Stop with the shortest timeout, not waited for."""
        self.killed = True
        if self.running:
            task = asyncio.ensure_future(self.link.stop(self.component_id, 0.001))
            task.add_done_callback(lambda t: t.cancelled() or t.exception())


class Agents:
    """The links to every host that runs a component of the system."""

    def __init__(self, config: SystemConfig, signer: TokenSigner | None, notify: LineSink,
                 cwd: Path | None = None) -> None:
        self.config = config
        self._signer = signer
        self._notify = notify
        self.config_path = config_path_for_agents(config, cwd) if remote_hosts(config) else ""
        self.links: dict[str, AgentLink] = {}

    async def attach_all(self) -> None:
        """Attach to the agent of every host a component or server runs on (CastError naming the first that fails)."""
        hosts = remote_hosts(self.config)
        for name in sorted(hosts):
            link = AgentLink(self.config.hosts[name], self.config, self.config_path, self._signer, self._notify)
            try:
                await link.attach()
            except CastError:
                await link.channel.close(None)
                raise
            self.links[name] = link

    def process(self, comp: ComponentConfig, env: Mapping[str, str], log_path: Path, sink: LineSink) -> RemoteProcess:
        """A process of ``comp`` to be started on its host."""
        return RemoteProcess(self.links[comp.host], comp.id, env, log_path, sink)

    def server_process(self, server: ServerConfig, routes: Mapping[str, str], await_run: str, log_path: Path,
                       sink: LineSink) -> RemoteProcess:
        """A server process (``cast serve``) to be started on its host."""
        proc = RemoteProcess(self.links[server.host], SERVER_PREFIX + server.name, {}, log_path, sink)
        proc.server, proc.routes, proc.await_run = server.name, dict(routes), await_run
        return proc

    async def renew(self, comp: ComponentConfig, token: str) -> None:
        """Send ``comp``'s fresh token to its agent (``Agent.Renew``); CastError if the host cannot take it."""
        await self.links[comp.host].renew(comp.id, token)

    async def close(self) -> None:
        """Detach from every agent."""
        for link in self.links.values():
            await link.close()
        self.links.clear()


def remote_hosts(config: SystemConfig) -> set[str]:
    """The hosts whose agents run a component or a server of the system."""
    return {c.host for c in config.remote_components} | {s.host for s in config.servers if s.host != LOCAL_HOST}


def probe_hosts(config: SystemConfig, secret: bytes | None, cwd: Path | None = None,
                timeout: float = 10.0) -> list[tuple[ComponentConfig | ServerConfig | None, str, str]]:
    """Ask each host's agent whether it is up and could start its components and servers.

    One (component or server, host, problem) per problem; None in the first place when the problem is
    the whole system's (the configuration is outside the working directory).
    """
    by_host: dict[str, list[ComponentConfig | ServerConfig]] = {}
    for comp in config.remote_components:
        by_host.setdefault(comp.host, []).append(comp)
    for server in config.servers:
        if server.host != LOCAL_HOST:
            by_host.setdefault(server.host, []).append(server)
    if not by_host:
        return []
    try:
        config_path = config_path_for_agents(config, cwd)
    except CastError as exc:
        return [(None, "", exc.message)]
    signer = TokenSigner(secret) if secret else None
    found: list[tuple[ComponentConfig | ServerConfig | None, str, str]] = []
    for name, placed in by_host.items():
        host = config.hosts[name]
        if signer is None and host.tls_ca is None:
            found.append((placed[0], name, "no system secret to sign the agent's token with: set CAST_SECRET_FILE "
                                           "(or CAST_SECRET) to the secret the agent was given with --secret-file"))
            continue
        try:
            channel = agent_channel(host)
        except OSError as exc:
            found.append((placed[0], name, f"cannot read the TLS files of hosts.{name}.tls: {exc}"))
            continue
        # Servers are asked about as server:NAME, the name the agent knows a started server by.
        by_id = {(SERVER_PREFIX + p.name if isinstance(p, ServerConfig) else p.id): p for p in placed}
        with channel:
            request = agent_pb2.ProbeRequest(config_path=config_path, sets=dict(config.variables),
                                             component_ids=list(by_id))
            try:
                reply = agent_pb2_grpc.AgentStub(channel).Probe(request, metadata=orchestrator_metadata(signer),
                                                                timeout=timeout)
            except grpc.RpcError as exc:
                found.append((placed[0], name, f"agent not usable: {describe_failure(host, exc)}"))
                continue
        found.extend((by_id.get(r.component_id), name, f"cannot start on host '{name}' ({reply.host}, root "
                                                       f"{reply.root}): {r.problem}")
                     for r in reply.results if not r.launchable)
    return found
