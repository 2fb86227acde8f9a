"""``cast run``: validate, serve, launch, supervise, show, and shut down in order.

The servers run in this process's event loop; each component runs as its own
process (or, with ``in_process: true``, on a thread of the server hosting its
SA). Shutdown, on Ctrl-C, SIGTERM, SIGHUP (its terminal closed) or the end of
``--for``: components in reverse start order (SIGTERM, so their runner calls
stop(); SIGKILL after the stop timeout), then in-process components, then the
servers.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cast.attach import AttachedTool
from cast.auth import TokenSigner
from cast.config.model import LOCAL_HOST, ComponentConfig, SystemConfig
from cast.core.sessions import ComponentState
from cast.orchestrator.output import Output
from cast.orchestrator.remote import Agents, remote_hosts
from cast.orchestrator.run_metrics import RunMetrics
from cast.orchestrator.run_tools import make_tools
from cast.orchestrator.security import LaunchSecurity, component_tls
from cast.orchestrator.servers import RemoteServer, ServerGroup
from cast.orchestrator.status import Snapshot, StatusTracker, render_status, render_summary
from cast.orchestrator.supervisor import Phase, Supervisor
from cast.runtime_dir import RuntimeDir

__all__ = ["Orchestrator", "RunOptions", "RunResult"]

# Variables a component must never inherit: with the secret it could forge any identity.
_PRIVATE_ENV = ("CAST_SECRET", "CAST_SECRET_FILE")
REMOTE_STATUS_S = 2.0
"""How often the live view asks servers on other hosts about their SAs."""
SESSIONS_END_S = 2.0
"""How long the final summary waits for the directory to see stopped components' sessions end."""


@dataclass
class RunOptions:
    """How to run a system."""

    run_for: float | None = None  # seconds after every component connected; None: until signalled
    runtime_dir: Path = field(default_factory=lambda: Path(".cast"))
    status_interval: float = 0.5
    metrics: str | None = None  # HOST:PORT to serve /metrics on (Prometheus); None: not served
    summary_json: Path | None = None
    foxglove: str | None = None  # HOST:PORT of the Foxglove live view (cast run --foxglove); None: no view
    record: Path | None = None  # the MCAP file to record the run to (cast run --record); None: no recording
    web: str | None = None  # HOST:PORT of the web view (cast run --web); None: no web view


@dataclass
class RunResult:
    """What a run ended with."""

    failures: list[str]
    snapshot: Snapshot | None
    connect_seconds: float | None = None

    @property
    def exit_code(self) -> int:
        """0 if every component ran and stopped cleanly, else 1."""
        return 1 if self.failures else 0


class Orchestrator:
    """Runs one system until it is told to stop."""

    def __init__(
        self, config: SystemConfig, options: RunOptions, output: Output, env: Mapping[str, str] | None = None
    ) -> None:
        self.config = config
        self.options = options
        self.output = output
        self.env = dict(os.environ if env is None else env)
        self.runtime = RuntimeDir(options.runtime_dir)
        self._stop = asyncio.Event()
        self._hung_up = False
        self._signer: TokenSigner | None = None
        self._security: LaunchSecurity | None = None
        self._servers: ServerGroup | None = None
        self.supervisor: Supervisor | None = None
        self.connected = threading.Event()  # set once every component has started (the barrier released)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread = 0

    @property
    def servers(self) -> ServerGroup:
        """The running servers (after :meth:`run` started them)."""
        assert self._servers is not None, "the system is not running"
        return self._servers

    def request_stop(self) -> None:
        """Begin the orderly shutdown (what Ctrl-C and SIGTERM do); callable from any thread."""
        if self._loop is not None and threading.get_ident() != self._loop_thread:
            self._loop.call_soon_threadsafe(self._stop.set)
        else:
            self._stop.set()

    def _on_signal(self) -> None:
        if self._stop.is_set() and self.supervisor is not None:
            # Asked twice: the user does not want to wait for stop() hooks any longer.
            self.output.notice("stopping now: killing every component")
            self.supervisor.kill_all()
        self._stop.set()

    def _contract(self, comp: ComponentConfig) -> dict[str, str]:
        assert self._signer is not None and self._servers is not None
        assert self._security is not None
        directory = self._servers.directory
        return {
            # A component on another host dials the directory's advertised address.
            "CAST_ENDPOINT": directory.config.address(directory.endpoint) if comp.remote else directory.endpoint,
            "CAST_COMPONENT_ID": comp.id,
            "CAST_SUBARCHITECTURE": comp.subarchitecture,
            "CAST_ARGS": json.dumps(comp.args),
            "CAST_START_BARRIER": "1",  # run() after every component's start() (cast.core.barrier)
            # CAST_TOKEN, and with a token ttl CAST_TOKEN_FILE (renewed), with TLS CAST_TLS_*.
            **self._security.contract(comp),
        }

    async def run(self) -> RunResult:
        """Run the system; return when it has shut down."""
        loop = asyncio.get_running_loop()

        def notices(tool: str) -> Callable[[str], None]:
            def notice(text: str) -> None:  # from the tool's thread too
                loop.call_soon_threadsafe(self.output.notice, f"{tool}: {text}")
            return notice

        # Made before anything starts, so that a taken port or an existing file ends the run at once.
        tools = make_tools(self.options.foxglove, self.options.record, notices, self.options.web)
        try:
            return await self._run(tools)
        finally:
            for tool in tools:
                await loop.run_in_executor(None, tool.close)

    async def _run(self, tools: Sequence[AttachedTool]) -> RunResult:
        self._prepare()
        loop = self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._handle_signals(loop, install=True)
        assert self._signer is not None and self._security is not None
        servers = self._servers = ServerGroup(self.config, self._signer)
        metrics = RunMetrics(servers, self.options.metrics, self.output.notice)  # bound before anything starts
        await servers.start()
        child_env = {k: v for k, v in self.env.items() if k not in _PRIVATE_ENV}
        agents: Agents | None = None
        try:
            agents = await self._attach_agents()
            if agents is not None and any(srv.host != LOCAL_HOST for srv in self.config.servers):
                await self._start_remote_servers(servers, agents)
        except BaseException:
            await servers.stop_remote(1.0)
            if agents is not None:
                await agents.close()
            await servers.stop()
            metrics.close()
            self.runtime.release()
            self._handle_signals(loop, install=False)
            raise
        supervisor = self.supervisor = Supervisor(
            self.config, self._contract, self.runtime.logs, self.output.component_line, self.output.notice, child_env,
            agents,
        )
        tracker = StatusTracker(self.config, servers, supervisor)
        self._publish(servers)
        failures: list[str] = []
        connect_seconds: float | None = None
        snapshot: Snapshot | None = None
        counted: dict[str, Any] = {}
        status_task: asyncio.Task[None] | None = None
        renew_task: asyncio.Future[None] | None = None
        watch_task: asyncio.Future[None] | None = None
        if agents is not None:
            self._security.remote = agents.renew  # tokens of components on other hosts go to their agents
        self._security.runs = supervisor.runs
        try:
            for tool in tools:  # before any component starts; off the loop that serves the tool's calls
                await loop.run_in_executor(None, tool.attach, servers.directory.endpoint, self._signer,
                                           component_tls(self.config))
            with self.output:
                if servers.remote:
                    watch_task = asyncio.ensure_future(self._watch_remote_servers(servers, failures))
                for comp in self.config.components:
                    if comp.in_process:
                        servers.start_in_process(comp)
                started = time.monotonic()
                supervisor.start_all()
                renew_task = asyncio.ensure_future(self._security.renew_forever())
                status_task = asyncio.ensure_future(self._show_status(tracker))
                missing = await self._wait_started(servers, supervisor)
                # Released even when some did not start in time (the run has failed then): the
                # others are not held back for good.
                servers.release_run()
                if missing:
                    failures.extend(missing)
                    self.output.notice(f"not started: {', '.join(missing)}")
                else:
                    self.connected.set()
                    connect_seconds = time.monotonic() - started
                    self._report_started(supervisor, connect_seconds)
                if self.options.run_for is not None and not self._stop.is_set():
                    loop.call_later(self.options.run_for, self._stop.set)
                await self._stop.wait()
                self.output.notice("stopping: components in reverse order, then the servers")
                await supervisor.stop_all(self.config.orchestrator.stop_timeout)
                await loop.run_in_executor(None, servers.stop_in_process)
                status_task.cancel()
                await self._wait_sessions_ended(servers)
                await tracker.refresh_remote()  # the SAs of servers on other hosts, still running
                snapshot = tracker.snapshot()
                counted = await metrics.snapshot()  # every component has stopped: the final counts
        finally:
            if status_task is not None:
                status_task.cancel()
            for task in (renew_task, watch_task):
                if task is not None:
                    task.cancel()
            await supervisor.stop_all(0.5)  # on an error path; a no-op after an orderly stop
            for tool in tools:  # it has seen the components' last changes; its watches end before the servers
                await loop.run_in_executor(None, tool.stop_watching)
            await servers.stop_remote(self.config.orchestrator.stop_timeout)  # then the servers, remote first
            if agents is not None:
                await agents.close()
            await servers.stop()
            metrics.close()
            self.runtime.release()
            self._handle_signals(loop, install=False)
        failures.extend(_component_failures(supervisor))
        if snapshot is not None:
            self.output.show(render_summary(snapshot, failures))
            if self.options.summary_json is not None:
                data = {**snapshot.to_json(), "failures": failures, "connect_seconds": connect_seconds,
                        "metrics": counted}
                self.options.summary_json.write_text(json.dumps(data, indent=2))
        return RunResult(failures, snapshot, connect_seconds)

    async def _start_remote_servers(self, servers: ServerGroup, agents: Agents) -> None:
        """Start the servers placed on other hosts through their agents; say where each listens."""
        started = time.monotonic()
        await servers.start_remote(agents, self.runtime.logs, self.output.component_line)
        for far in servers.remote:
            self.output.notice(f"server {far.config.name} on host {far.config.host}: listening on {far.endpoint}, "
                               f"reached at {far.address} ({time.monotonic() - started:.2f} s)")

    async def _watch_remote_servers(self, servers: ServerGroup, failures: list[str]) -> None:
        """A server on another host that ends (or whose host is lost) before the stop ends the system.

        Its SAs are gone for every component, and a fresh server would have lost their entries unless
        it journals: the run fails and says why, as when a local server cannot serve (docs/multihost.md).
        """
        ended = asyncio.as_completed([asyncio.ensure_future(self._ended(far)) for far in servers.remote])
        for next_end in ended:
            far, code = await next_end
            if self._stop.is_set():
                return
            how = (f"host '{far.config.host}' was lost" if far.process.host_lost
                   else f"it exited with {'signal ' + str(-code) if code < 0 else 'code ' + str(code)}")
            failures.append(f"server {far.config.name} on host {far.config.host}: {how}")
            self.output.notice(f"server {far.config.name} on host {far.config.host} ended: {how}; its SAs "
                               f"({', '.join(far.config.subarchitectures)}) are gone, so the system stops")
            self._stop.set()
            return

    @staticmethod
    async def _ended(far: RemoteServer) -> tuple[RemoteServer, int]:
        return far, await far.process.wait()

    async def _attach_agents(self) -> Agents | None:
        """Attach to the agent of every host that runs a component or a server (None if all is local)."""
        if not remote_hosts(self.config):
            return None
        assert self._signer is not None
        agents = Agents(self.config, self._signer, lambda host, text: self.output.notice(f"host {host}: {text}"))
        started = time.monotonic()
        try:
            await agents.attach_all()
        except BaseException:
            await agents.close()
            raise
        hosts = ", ".join(f"{name} ({link.host.agent}, {link.attached.host if link.attached else '?'})"
                          for name, link in agents.links.items())
        self.output.notice(f"attached to the agents of {hosts} in {time.monotonic() - started:.2f} s")
        return agents

    def _prepare(self) -> None:
        """Claim the runtime directory, make the secret and the launch security, extend sys.path."""
        self.runtime.claim()
        secret = self.env.get("CAST_SECRET", "").encode() or None
        if not secret and self.env.get("CAST_SECRET_FILE"):
            # The system secret the agents were given with --secret-file (docs/multihost.md).
            secret = Path(self.env["CAST_SECRET_FILE"]).read_bytes().strip() or None
        if secret:
            self.runtime.write_secret(secret)
        else:
            secret = self.runtime.new_secret()
        self._signer = TokenSigner(secret)
        self._security = LaunchSecurity(self.config, self._signer, self.runtime.path)
        # User policy classes and in-process components import from python_path.
        sys.path[:0] = [str(p) for p in self.config.python_path if str(p) not in sys.path]

    def _on_hangup(self) -> None:
        # The terminal closed (SIGHUP): stop as on SIGTERM, with nowhere left to show it. A closed window
        # sends it twice (the kernel to the foreground job, the shell to its jobs): not a second Ctrl-C.
        if self._hung_up:
            return
        self._hung_up = True
        self.output.hang_up()
        self._on_signal()

    def _handle_signals(self, loop: asyncio.AbstractEventLoop, install: bool) -> None:
        handlers = {signal.SIGINT: self._on_signal, signal.SIGTERM: self._on_signal, signal.SIGHUP: self._on_hangup}
        for sig, handler in handlers.items():
            # Not in the main thread (an orchestrator embedded in a test): the caller stops it.
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                if install:
                    loop.add_signal_handler(sig, handler)
                else:
                    loop.remove_signal_handler(sig)

    def _publish(self, servers: ServerGroup) -> None:
        """Record the running system in the runtime directory (for the tools) and say where it runs."""
        assert self._security is not None
        self.runtime.write_state({
            "system": self.config.name,
            "endpoint": servers.directory.endpoint,
            "servers": {s.config.name: {"endpoint": s.endpoint, "subarchitectures": s.config.subarchitectures,
                                        "advertise": s.config.address(s.endpoint)}
                        for s in servers.servers}
                       | {s.config.name: {"endpoint": s.address, "subarchitectures": s.config.subarchitectures,
                                          "advertise": s.address, "host": s.config.host} for s in servers.remote},
            "hosts": {h.name: h.agent for h in self.config.hosts.values()},
            "config": str(Path(self.config.source).resolve()),
            "tls": self._security.tls_state(),  # so `cast ls` & co. reach a TLS system unaided
        })
        self.output.known_components([c.id for c in self.config.components])
        self.output.notice(
            f"system '{self.config.name}': {len(self.config.subarchitectures)} SAs on "
            + ", ".join([f"{s.config.name} {s.endpoint}" for s in servers.servers]
                        + [f"{s.config.name} {s.address} (host {s.config.host})" for s in servers.remote])
            + f"; runtime directory {self.runtime.path}"
        )

    def _report_started(self, supervisor: Supervisor, seconds: float) -> None:
        count = sum(1 for c in self.config.components if not c.manual)
        finished = [cid for cid, sup in supervisor.components.items() if sup.phase is Phase.EXITED]
        failed = [cid for cid, sup in supervisor.components.items() if sup.phase is Phase.FAILED]
        if not finished and not failed:
            self.output.notice(f"all {count} components started in {seconds:.2f} s; run() released")
            return
        # A component that did its work and exited 0 is not a failure to connect: say which is which.
        parts = [f"{count - len(finished) - len(failed)} of {count} components running after {seconds:.2f} s"]
        if finished:
            parts.append(f"finished already (exit code 0): {', '.join(finished)}")
        if failed:
            parts.append(f"failed: {', '.join(failed)}")
        self.output.notice("; ".join(parts))

    async def _wait_started(self, servers: ServerGroup, supervisor: Supervisor) -> list[str]:
        """Wait until every launched component has finished start(); what is wrong with those that did not.

        Started means STARTED (waiting at the barrier), or past it: a component of another library
        that does not wait reports RUNNING at once. One that exited or failed is not waited for.
        """
        expected = [c.id for c in self.config.components if not c.manual]
        past_start = (ComponentState.STARTED, ComponentState.RUNNING, ComponentState.STOPPING)
        timeout = self.config.orchestrator.connect_timeout
        deadline = time.monotonic() + timeout
        while True:
            # A component registers with each server it uses; an in-process one only with its own.
            seen: list[Any] = [i for server in servers.servers for i in server.system.sessions.components()
                               if i.session_id]
            # In-process components of a server on another host register only there: ask it.
            seen += [i for i in await servers.remote_components() if i.session_id] if servers.remote else []
            connected = {i.id for i in seen}
            started = {i.id for i in seen if i.state in past_start}
            waiting = [
                cid for cid in expected
                if cid not in started
                and not (cid in supervisor.components and supervisor.components[cid].phase in (Phase.FAILED,
                                                                                                 Phase.EXITED))
            ]
            if not waiting or self._stop.is_set():
                return []
            if time.monotonic() > deadline:
                return [f"{cid} did not finish start() within {timeout:.0f} s" if cid in connected
                        else f"{cid} did not connect within {timeout:.0f} s" for cid in waiting]
            await asyncio.sleep(0.05)

    async def _wait_sessions_ended(self, servers: ServerGroup) -> None:
        """Wait, briefly, until the directory has seen every stopped component's session end.

        A component's process can exit a moment before the directory's server notices its
        heartbeat stream close; the final summary is taken after that, so it shows each one
        disconnected rather than the state of a race. Manual components were not stopped by the
        run and are not waited for; the wait is bounded, since a summary must still be printed.
        """
        ours = {c.id for c in self.config.components if not c.manual}
        deadline = time.monotonic() + SESSIONS_END_S
        while time.monotonic() < deadline:
            if not any(i.session_id for i in servers.directory.system.sessions.components() if i.id in ours):
                return
            await asyncio.sleep(0.02)

    async def _show_status(self, tracker: StatusTracker) -> None:
        if not self.output.live_status:
            return
        asked = 0.0
        while True:
            if self._servers is not None and self._servers.remote and time.monotonic() - asked >= REMOTE_STATUS_S:
                # Servers on other hosts are asked over the network: less often than the view is drawn.
                asked = time.monotonic()
                await tracker.refresh_remote()
            self.output.update_status(render_status(tracker.snapshot()))
            await asyncio.sleep(self.options.status_interval)


def _component_failures(supervisor: Supervisor) -> list[str]:
    """What went wrong with each component: crashes, start failures, unclean stops."""
    failures = []
    for sup in supervisor.components.values():
        cid = sup.config.id
        if sup.crashes:
            codes = ", ".join(str(c) for c in sup.crashes)
            failures.append(f"{cid} crashed {len(sup.crashes)} time(s) (exit codes {codes})")
        if sup.host_losses:
            failures.append(f"{cid}: host '{sup.config.host}' lost ({sup.host_losses} time(s))"
                            + ("; not running at the end" if sup.phase is Phase.FAILED else "; restarted"))
        if sup.phase is Phase.FAILED and sup.error and not sup.error.startswith("host '"):
            failures.append(f"{cid}: {sup.error}")
        if sup.stop_code not in (None, 0):
            failures.append(f"{cid} exited with code {sup.stop_code} when stopped"
                            + (" (killed)" if sup.process is not None and sup.process.killed else ""))
    return failures
