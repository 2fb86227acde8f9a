"""Components on other hosts: the orchestrator's side of ``cast agent`` (docs/multihost.md).

For each host under ``hosts:`` that runs a component, an :class:`AgentLink`
attaches to that host's agent (``cast.v1.Agent``, through the generated stubs
only: the orchestrator never imports ``cast.agent``) with a lease, keeps the
session alive and acknowledges its events. A :class:`RemoteProcess` stands for
one component launched there and behaves like a local
:class:`cast.orchestrator.process.ComponentProcess` to the supervisor: its
output lines arrive on the Attach stream and go to the same log file and
terminal sink, its exit arrives as a ``ProcessExit`` event, and stopping it is
``Agent.Stop`` (SIGTERM, SIGKILL after the timeout, on its host).

Trust: every call carries a privileged token for the identity ``orchestrator``
signed with the system secret (the agent was given the same secret with
``--secret-file``), and/or TLS with the host's ``tls:`` files. The
configuration is named relative to the orchestrator's working directory, which
must be the checkout or install each agent has under ``--root``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any

import grpc
import grpc.aio

from cast.auth import TokenSigner
from cast.config.model import ComponentConfig, HostConfig, SystemConfig
from cast.core.records import Identity
from cast.errors import CastError, InvalidArgumentError, UnavailableError
from cast.orchestrator.process import LineSink
from cast.v1 import agent_pb2, agent_pb2_grpc

__all__ = ["ORCHESTRATOR_ID", "AgentLink", "Agents", "RemoteProcess", "config_path_for_agents", "probe_hosts"]

ORCHESTRATOR_ID = "orchestrator"
"""The identity of the token an orchestrator presents to agents (privileged)."""

_CALL_TIMEOUT = 30.0


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


def _credentials(host: HostConfig) -> grpc.ChannelCredentials | None:
    if host.tls_ca is None:
        return None
    ca = host.tls_ca.read_bytes()
    if host.tls_cert is not None and host.tls_key is not None:
        return grpc.ssl_channel_credentials(ca, host.tls_key.read_bytes(), host.tls_cert.read_bytes())
    return grpc.ssl_channel_credentials(ca)


def _metadata(signer: TokenSigner | None) -> tuple[tuple[str, str], ...]:
    if signer is None:
        return ()
    return (("authorization", f"Bearer {signer.issue(Identity(ORCHESTRATOR_ID, '', True))}"),)


def _describe(host: HostConfig, exc: grpc.RpcError) -> str:
    code = exc.code()
    detail = exc.details() or ""
    hint = ""
    if code is grpc.StatusCode.UNAUTHENTICATED:
        hint = (" (the agent trusts another secret: give cast run the system secret the agent was given with "
                "--secret-file, in CAST_SECRET_FILE or CAST_SECRET)")
    elif code is grpc.StatusCode.UNAVAILABLE:
        hint = f" (is `cast agent --listen {host.agent}` running there, and reachable from here?)"
    return f"host '{host.name}' (agent {host.agent}): {code.name}: {detail}{hint}"


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
        self._exit: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        self.argv: list[str] = []

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
        self.pid, self.argv = reply.pid, list(reply.argv)

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

    def lost(self) -> None:
        """The agent's session ended: this process is gone (the agent stops it after the lease)."""
        if not self._exit.done():
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


class AgentLink:
    """The session with one host's agent: Attach (lease, keepalives with acks), Launch, Stop."""

    def __init__(self, host: HostConfig, config: SystemConfig, config_path: str, signer: TokenSigner | None,
                 notify: LineSink | None = None) -> None:
        self.host = host
        self.config = config
        self.config_path = config_path
        self._signer = signer
        self._notify = notify
        self.channel = self._open()
        self.stub = agent_pb2_grpc.AgentStub(self.channel)
        self.attached: agent_pb2.AgentAttached | None = None
        self.processes: dict[str, RemoteProcess] = {}
        self._ack = 0
        self._closing = False
        self._reader: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()

    def _open(self) -> grpc.aio.Channel:
        credentials = _credentials(self.host)
        if credentials is not None:
            return grpc.aio.secure_channel(self.host.agent, credentials)
        return grpc.aio.insecure_channel(self.host.agent)

    @property
    def lease_ms(self) -> int:
        """The agent keeps the system's processes this long without hearing from us."""
        return self.config.orchestrator.lease_ms

    async def _requests(self) -> AsyncIterator[agent_pb2.AttachRequest]:
        yield agent_pb2.AttachRequest(system=self.config.name, lease_ms=self.lease_ms,
                                      grace_ms=max(1, int(self.config.orchestrator.stop_timeout * 1000)))
        while not self._closing:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), self.lease_ms / 3000)
            if self._closing:
                return
            yield agent_pb2.AttachRequest(ack_seq=self._ack)

    async def attach(self) -> agent_pb2.AgentAttached:
        """Open the session; CastError naming the host if the agent is unreachable or refuses."""
        call = self.stub.Attach(self._requests(), metadata=_metadata(self._signer))
        try:
            first: Any = await asyncio.wait_for(call.read(), _CALL_TIMEOUT)
        except grpc.RpcError as exc:
            raise UnavailableError(f"cannot attach to {_describe(self.host, exc)}") from exc
        except TimeoutError as exc:
            call.cancel()
            raise UnavailableError(f"host '{self.host.name}' (agent {self.host.agent}) did not answer") from exc
        if not isinstance(first, agent_pb2.AgentEvent) or first.WhichOneof("event") != "attached":
            raise UnavailableError(f"host '{self.host.name}': the agent ended the session at once")
        attached: agent_pb2.AgentAttached = first.attached
        self.attached = attached
        self._reader = asyncio.ensure_future(self._read(call))
        return attached

    async def _read(self, call: grpc.aio.StreamStreamCall) -> None:  # type: ignore[type-arg]
        try:
            while True:  # read() as for the first event: grpc.aio does not mix read() and iteration
                event: Any = await call.read()
                if not isinstance(event, agent_pb2.AgentEvent):
                    if not self._closing and self._notify is not None:
                        self._notify(self.host.name, f"lost the agent at {self.host.agent}: it ended the session")
                    break
                self._ack = max(self._ack, event.seq)
                kind = event.WhichOneof("event")
                if kind == "output":
                    proc = self.processes.get(event.output.component_id)
                    if proc is not None:
                        proc.line(event.output.text)
                elif kind == "exit":
                    proc = self.processes.get(event.exit.component_id)
                    if proc is not None and proc.pid == event.exit.pid:
                        proc.exited(event.exit)
        except grpc.RpcError as exc:
            if not self._closing and self._notify is not None:
                self._notify(self.host.name, f"lost the agent: {_describe(self.host, exc)}")
        finally:
            if not self._closing:
                for proc in self.processes.values():
                    proc.lost()

    async def launch(self, proc: RemoteProcess) -> agent_pb2.LaunchResponse:
        """``Agent.Launch`` for ``proc``'s component."""
        self.processes[proc.component_id] = proc
        request = agent_pb2.LaunchRequest(system=self.config.name, config_path=self.config_path,
                                          sets=dict(self.config.variables), component_id=proc.component_id,
                                          env=proc.env)
        try:
            return await self.stub.Launch(request, metadata=_metadata(self._signer), timeout=_CALL_TIMEOUT)
        except grpc.RpcError as exc:
            raise CastError(f"cannot launch on {_describe(self.host, exc)}") from exc

    async def stop(self, component_id: str, timeout: float) -> agent_pb2.StopResponse:
        """``Agent.Stop``: SIGTERM, SIGKILL after ``timeout`` seconds."""
        request = agent_pb2.StopRequest(system=self.config.name, component_id=component_id,
                                        timeout_ms=max(1, int(timeout * 1000)))
        try:
            return await self.stub.Stop(request, metadata=_metadata(self._signer), timeout=timeout + _CALL_TIMEOUT)
        except grpc.RpcError as exc:
            raise CastError(f"cannot stop {component_id} on {_describe(self.host, exc)}") from exc

    async def close(self) -> None:
        """End the session cleanly (its processes were stopped already) and close the channel."""
        self._closing = True
        self._wake.set()
        if self._reader is not None:
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(self._reader), 2.0)
            self._reader.cancel()
        await self.channel.close(None)


class Agents:
    """The links to every host that runs a component of the system."""

    def __init__(self, config: SystemConfig, signer: TokenSigner | None, notify: LineSink,
                 cwd: Path | None = None) -> None:
        self.config = config
        self._signer = signer
        self._notify = notify
        self.config_path = config_path_for_agents(config, cwd) if config.remote_components else ""
        self.links: dict[str, AgentLink] = {}

    async def attach_all(self) -> None:
        """Attach to the agent of every host a component runs on (CastError naming the first that fails)."""
        hosts = {c.host for c in self.config.remote_components}
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

    async def close(self) -> None:
        """Detach from every agent."""
        for link in self.links.values():
            await link.close()
        self.links.clear()


def probe_hosts(config: SystemConfig, secret: bytes | None, cwd: Path | None = None,
                timeout: float = 10.0) -> list[tuple[ComponentConfig | None, str, str]]:
    """Ask each host's agent whether it is up and could launch its components: (component, host, problem) each."""
    remote = config.remote_components
    if not remote:
        return []
    try:
        config_path = config_path_for_agents(config, cwd)
    except CastError as exc:
        return [(None, "", exc.message)]
    signer = TokenSigner(secret) if secret else None
    found: list[tuple[ComponentConfig | None, str, str]] = []
    by_host: dict[str, list[ComponentConfig]] = {}
    for comp in remote:
        by_host.setdefault(comp.host, []).append(comp)
    for name, comps in by_host.items():
        host = config.hosts[name]
        if signer is None and host.tls_ca is None:
            found.append((comps[0], name, "no system secret to sign the agent's token with: set CAST_SECRET_FILE "
                                          "(or CAST_SECRET) to the secret the agent was given with --secret-file"))
            continue
        try:
            credentials = _credentials(host)
        except OSError as exc:
            found.append((comps[0], name, f"cannot read the TLS files of hosts.{name}.tls: {exc}"))
            continue
        channel = (grpc.secure_channel(host.agent, credentials) if credentials is not None
                   else grpc.insecure_channel(host.agent))
        with channel:
            stub = agent_pb2_grpc.AgentStub(channel)
            request = agent_pb2.ProbeRequest(config_path=config_path, sets=dict(config.variables),
                                             component_ids=[c.id for c in comps])
            try:
                reply = stub.Probe(request, metadata=_metadata(signer), timeout=timeout)
            except grpc.RpcError as exc:
                found.append((comps[0], name, f"agent not usable: {_describe(host, exc)}"))
                continue
        by_id = {c.id: c for c in comps}
        found.extend((by_id.get(r.component_id), name, f"cannot launch on host '{name}' ({reply.host}, root "
                                                       f"{reply.root}): {r.problem}")
                     for r in reply.results if not r.launchable)
    return found
