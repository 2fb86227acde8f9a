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
import time
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any

import grpc
import grpc.aio
from grpc_health.v1 import health_pb2, health_pb2_grpc

from cast.auth import TokenSigner
from cast.config.model import LOCAL_HOST, ComponentConfig, HostConfig, ServerConfig, SystemConfig
from cast.core.records import Identity
from cast.errors import CastError, InvalidArgumentError, UnavailableError
from cast.orchestrator.process import LineSink
from cast.v1 import agent_pb2, agent_pb2_grpc

__all__ = [
    "ORCHESTRATOR_ID", "SERVER_PREFIX", "AgentLink", "Agents", "RemoteProcess", "config_path_for_agents",
    "probe_hosts", "remote_hosts",
]

SERVER_PREFIX = "server:"
"""A server started through an agent is known there as ``server:NAME``."""

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


class AgentLink:
    """The session with one host's agent: Attach (lease, keepalives with acks), Launch, Stop.

    The session survives a broken stream: the link attaches again (with backoff) and, within the
    lease, resumes the agent's session, which replays every event not acknowledged yet (events at
    or below the last one received are skipped, so nothing comes twice). A host not heard from
    for a lease (no event and no answer to the health checks made every :attr:`check_s`), or whose
    agent answers with a new session (it restarted), is *lost*: its components end as lost with it
    (:meth:`lose`) and are not restarted while it is gone; the link keeps trying to attach, and once
    a new session is open :attr:`back` is set and the supervisor restarts them under their restart
    policy.
    """

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
        self._tasks: list[asyncio.Task[None]] = []
        self._call: grpc.aio.StreamStreamCall | None = None  # type: ignore[type-arg]
        self._wake = asyncio.Event()
        self.heard = time.monotonic()  # when the agent last answered (an event or a health check)
        self.lost = False
        self.back = asyncio.Event()  # set while the host is attached (cleared when it is lost)
        self.back.set()
        self.losses = 0
        self.lost_at = 0.0

    def _open(self) -> grpc.aio.Channel:
        credentials = _credentials(self.host)
        options = [("grpc.initial_reconnect_backoff_ms", 200), ("grpc.min_reconnect_backoff_ms", 200),
                   ("grpc.max_reconnect_backoff_ms", 1000)]
        if credentials is not None:
            return grpc.aio.secure_channel(self.host.agent, credentials, options=options)
        return grpc.aio.insecure_channel(self.host.agent, options=options)

    @property
    def lease_ms(self) -> int:
        """The agent keeps the system's processes this long without hearing from us."""
        return self.config.orchestrator.lease_ms

    @property
    def check_s(self) -> float:
        """How often the agent's health is checked (and how long an answer is waited for)."""
        return min(1.0, self.lease_ms / 4000)

    def _say(self, text: str) -> None:
        if self._notify is not None:
            self._notify(self.host.name, text)

    async def _requests(self, ack: int) -> AsyncIterator[agent_pb2.AttachRequest]:
        yield agent_pb2.AttachRequest(system=self.config.name, lease_ms=self.lease_ms, ack_seq=ack,
                                      grace_ms=max(1, int(self.config.orchestrator.stop_timeout * 1000)))
        while not self._closing:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), self.lease_ms / 3000)
            if self._closing:
                return
            yield agent_pb2.AttachRequest(ack_seq=self._ack)

    async def _session(self, timeout: float) -> tuple[Any, agent_pb2.AgentAttached]:
        """Attach once: the call and its attached event; UnavailableError naming the host otherwise."""
        call = self.stub.Attach(self._requests(self._ack), metadata=_metadata(self._signer))
        try:
            first: Any = await asyncio.wait_for(call.read(), timeout)
        except grpc.RpcError as exc:
            raise UnavailableError(f"cannot attach to {_describe(self.host, exc)}") from exc
        except TimeoutError as exc:
            call.cancel()
            raise UnavailableError(f"host '{self.host.name}' (agent {self.host.agent}) did not answer") from exc
        except asyncio.CancelledError as exc:  # its channel was replaced (the host was lost)
            if self._closing:
                raise
            raise UnavailableError(f"host '{self.host.name}': the attempt to attach was cancelled") from exc
        if not isinstance(first, agent_pb2.AgentEvent) or first.WhichOneof("event") != "attached":
            call.cancel()
            raise UnavailableError(f"host '{self.host.name}': the agent ended the session at once")
        self.heard = time.monotonic()
        return call, first.attached

    async def attach(self) -> agent_pb2.AgentAttached:
        """Open the session; CastError naming the host if the agent is unreachable or refuses."""
        call, attached = await self._session(_CALL_TIMEOUT)
        self.attached = attached
        self._call = call
        self._tasks = [asyncio.ensure_future(self._keep(call)), asyncio.ensure_future(self._check())]
        return attached

    async def _keep(self, call: Any) -> None:
        """Read the session's events; when the stream breaks, attach again (forever, with backoff)."""
        while not self._closing:
            await self._read(call)
            if self._closing:
                return
            call = await self._reattach()

    async def _read(self, call: Any) -> None:
        try:
            while True:  # read() as for the first event: grpc.aio does not mix read() and iteration
                event: Any = await call.read()
                if not isinstance(event, agent_pb2.AgentEvent):
                    break
                self.heard = time.monotonic()
                if event.seq and event.seq <= self._ack:
                    continue  # replayed after a re-attach, and received already
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
        except grpc.RpcError:
            pass  # the stream broke: _keep attaches again, and the host is lost only after a lease
        except asyncio.CancelledError:
            if self._closing:
                raise

    async def _reattach(self) -> Any:
        """Attach again until it works; a new session (not resumed) means the host was lost."""
        delay = 0.1
        new_session = False  # the agent answered with a new session: it restarted, its processes are gone
        while True:
            if self._closing:
                raise asyncio.CancelledError
            try:
                call, attached = await self._session(max(0.5, self.lease_ms / 3000))
                if not attached.resumed:
                    new_session = True
                    self._ack = 0  # its events start at 1 again (the agent ignored our old ack)
            except CastError:
                await asyncio.sleep(delay)
                delay = min(delay * 2, max(0.2, self.lease_ms / 3000))
                continue
            self.attached = attached
            self._call = call
            if not new_session and not self.lost:
                self._say(f"attached again to the agent at {self.host.agent} within the lease: session resumed, "
                          "nothing restarted")
                return call
            if not self.lost:
                self.lose("its agent restarted (a new session: its processes are gone)")
            for info in attached.running:  # a resumed session of a host declared lost: stop what is left
                with contextlib.suppress(CastError):
                    await self.stop(info.component_id, self.config.orchestrator.stop_timeout)
            self.lost = False
            self._say(f"back: attached to the agent at {self.host.agent} again {time.monotonic() - self.lost_at:.1f} s "
                      "after it was lost; its components restart under their restart policy")
            self.back.set()
            return call

    async def _check(self) -> None:
        """Ask the agent's health every :attr:`check_s`; a lease without an answer loses the host."""
        while not self._closing:
            await asyncio.sleep(self.check_s)
            if self._closing:
                return
            if not self.lost:
                silent = time.monotonic() - self.heard
                if silent > self.lease_ms / 1000:
                    self.lose(f"no answer from its agent at {self.host.agent} for {silent:.1f} s (lease "
                              f"{self.lease_ms / 1000:.1f} s)")
                    continue
            try:
                await health_pb2_grpc.HealthStub(self.channel).Check(health_pb2.HealthCheckRequest(),
                                                                     timeout=self.check_s)
                self.heard = time.monotonic()
            except grpc.RpcError:
                pass
            except asyncio.CancelledError:  # its channel was replaced (the host was lost)
                if self._closing:
                    raise

    def lose(self, why: str) -> None:
        """The host is lost: say so, naming its components; they end as lost; the link starts afresh."""
        self.lost, self.lost_at = True, time.monotonic()
        self.losses += 1
        self.back.clear()
        names = sorted(cid for cid, proc in self.processes.items() if proc.running)
        self._say(f"lost: {why}; its components failed: {', '.join(names) or 'none was running'}")
        for proc in list(self.processes.values()):
            proc.lost(host=True)
        if self._call is not None:
            self._call.cancel()  # a stream over a cut link: _keep attaches again, on a new channel
        old, self.channel = self.channel, self._open()
        self.stub = agent_pb2_grpc.AgentStub(self.channel)
        task = asyncio.ensure_future(old.close(None))
        task.add_done_callback(lambda t: t.cancelled() or t.exception())

    async def launch(self, proc: RemoteProcess) -> agent_pb2.LaunchResponse:
        """``Agent.Launch`` for ``proc``'s component."""
        if self.lost:
            raise UnavailableError(f"cannot launch {proc.component_id}: host '{self.host.name}' is lost")
        self.processes[proc.component_id] = proc
        if proc.server:
            request = agent_pb2.LaunchRequest(system=self.config.name, config_path=self.config_path,
                                              sets=dict(self.config.variables), server=proc.server,
                                              routes=proc.routes, await_run=proc.await_run)
        else:
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
        for task in self._tasks:
            if not task.done():
                with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                    await asyncio.wait_for(asyncio.shield(task), 2.0)
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        await self.channel.close(None)


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

    async def close(self) -> None:
        """Detach from every agent."""
        for link in self.links.values():
            await link.close()
        self.links.clear()


def remote_hosts(config: SystemConfig) -> set[str]:
    """The hosts whose agents run a component or a server of the system."""
    return {c.host for c in config.remote_components} | {s.host for s in config.servers if s.host != LOCAL_HOST}


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
