"""The orchestrator's session with one host's agent (``cast.v1.Agent``): Attach, Launch, Stop, Renew.

Through the generated stubs only: the orchestrator never imports ``cast.agent``.
Trust: every call carries a privileged token for the identity ``orchestrator``
signed with the system secret (the agent was given the same secret with
``--secret-file``), and/or TLS with the host's ``tls:`` files.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Any

import grpc
import grpc.aio
from grpc_health.v1 import health_pb2, health_pb2_grpc

from cast.auth import TokenSigner
from cast.config.model import HostConfig, SystemConfig
from cast.core.records import Identity
from cast.errors import CastError, UnavailableError
from cast.orchestrator.process import LineSink
from cast.v1 import agent_pb2, agent_pb2_grpc

if TYPE_CHECKING:
    from cast.orchestrator.remote import RemoteProcess

__all__ = ["ORCHESTRATOR_ID", "AgentLink", "agent_channel", "describe_failure", "orchestrator_metadata"]

ORCHESTRATOR_ID = "orchestrator"
"""The identity of the token an orchestrator presents to agents (privileged)."""

CALL_TIMEOUT = 30.0
"""How long a Launch, Stop or Renew may take before the agent counts as unreachable."""


def _credentials(host: HostConfig) -> grpc.ChannelCredentials | None:
    """The TLS credentials of ``host``'s ``tls:`` files, or None for plaintext (OSError if unreadable)."""
    if host.tls_ca is None:
        return None
    ca = host.tls_ca.read_bytes()
    if host.tls_cert is not None and host.tls_key is not None:
        return grpc.ssl_channel_credentials(ca, host.tls_key.read_bytes(), host.tls_cert.read_bytes())
    return grpc.ssl_channel_credentials(ca)


def orchestrator_metadata(signer: TokenSigner | None) -> tuple[tuple[str, str], ...]:
    """The ``orchestrator`` token every call to an agent, or to a server, carries (none when trust is TLS only)."""
    if signer is None:
        return ()
    return (("authorization", f"Bearer {signer.issue(Identity(ORCHESTRATOR_ID, '', True))}"),)


def describe_failure(host: HostConfig, exc: grpc.RpcError) -> str:
    """A failed call to ``host``'s agent, with what to check."""
    code = exc.code()
    detail = exc.details() or ""
    hint = ""
    if code is grpc.StatusCode.UNAUTHENTICATED:
        hint = (" (the agent trusts another secret: give cast run the system secret the agent was given with "
                "--secret-file, in CAST_SECRET_FILE or CAST_SECRET)")
    elif code is grpc.StatusCode.UNAVAILABLE:
        hint = f" (is `cast agent --listen {host.agent}` running there, and reachable from here?)"
    return f"host '{host.name}' (agent {host.agent}): {code.name}: {detail}{hint}"


def agent_channel(host: HostConfig, options: list[tuple[str, Any]] | None = None) -> grpc.Channel:
    """A blocking channel to ``host``'s agent, TLS when the host has ``tls:`` (OSError if unreadable)."""
    credentials = _credentials(host)
    if credentials is not None:
        return grpc.secure_channel(host.agent, credentials, options=options)
    return grpc.insecure_channel(host.agent, options=options)


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
        call = self.stub.Attach(self._requests(self._ack), metadata=orchestrator_metadata(self._signer))
        try:
            first: Any = await asyncio.wait_for(call.read(), timeout)
        except grpc.RpcError as exc:
            raise UnavailableError(f"cannot attach to {describe_failure(self.host, exc)}") from exc
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
        call, attached = await self._session(CALL_TIMEOUT)
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
            # With expiring tokens the agent keeps the token file on its host; Renew rewrites it.
            request = agent_pb2.LaunchRequest(system=self.config.name, config_path=self.config_path,
                                              sets=dict(self.config.variables), component_id=proc.component_id,
                                              env=proc.env, token_file=self.config.auth.token_ttl > 0)
        try:
            return await self.stub.Launch(request, metadata=orchestrator_metadata(self._signer), timeout=CALL_TIMEOUT)
        except grpc.RpcError as exc:
            raise CastError(f"cannot launch on {describe_failure(self.host, exc)}") from exc

    async def stop(self, component_id: str, timeout: float) -> agent_pb2.StopResponse:
        """``Agent.Stop``: SIGTERM, SIGKILL after ``timeout`` seconds."""
        request = agent_pb2.StopRequest(system=self.config.name, component_id=component_id,
                                        timeout_ms=max(1, int(timeout * 1000)))
        try:
            return await self.stub.Stop(request, metadata=orchestrator_metadata(self._signer),
                                        timeout=timeout + CALL_TIMEOUT)
        except grpc.RpcError as exc:
            raise CastError(f"cannot stop {component_id} on {describe_failure(self.host, exc)}") from exc

    async def renew(self, component_id: str, token: str) -> None:
        """``Agent.Renew``: the component's token file on its host gets ``token``."""
        if self.lost:
            raise UnavailableError(f"cannot renew the token of {component_id}: host '{self.host.name}' is lost")
        request = agent_pb2.RenewRequest(system=self.config.name, component_id=component_id, token=token)
        try:
            await self.stub.Renew(request, metadata=orchestrator_metadata(self._signer), timeout=CALL_TIMEOUT)
        except grpc.RpcError as exc:
            raise CastError(f"cannot renew the token of {component_id} on {describe_failure(self.host, exc)}") from exc

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
