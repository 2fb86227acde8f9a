"""The agent's process table: the sessions of the systems it serves and the processes it started for them.

Processes are started exactly as ``cast run`` starts them
(:class:`cast.orchestrator.process.ComponentProcess`): each in its own process
group, through the PR_SET_PDEATHSIG trampoline so that they die with the agent,
stopped with SIGTERM to the group and SIGKILL after a timeout. Their lines,
exits and resource samples become events of their system's session. A
reaper stops every process of a system whose session's lease ran out, so a
dead orchestrator leaves nothing behind.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import tempfile
from collections.abc import Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cast.agent.launch import LaunchPlan
from cast.agent.resources import ResourceMeter
from cast.agent.sessions import SystemSession
from cast.auth import write_token_file
from cast.errors import AlreadyExistsError, LockedError, NotFoundError
from cast.orchestrator.process import ComponentProcess
from cast.v1 import agent_pb2

__all__ = ["AgentProcess", "ProcessTable"]

log = logging.getLogger("cast.agent")

SAMPLE_PERIOD_S = 1.0


@dataclass
class AgentProcess:
    """One started component process and how its end is reported."""

    system: str
    process: ComponentProcess
    stop_reason: str = ""  # set when the agent stops it: "stopped", "lease expired", "agent stopping"
    token_file: Path | None = None  # CAST_TOKEN_FILE when launched with token_file (rewritten by renew)
    exit: agent_pb2.ProcessExit | None = None
    done: asyncio.Event = field(default_factory=asyncio.Event)

    @property
    def component_id(self) -> str:
        """The component's id."""
        return self.process.component_id


def _exit_of(proc: AgentProcess, code: int) -> agent_pb2.ProcessExit:
    return agent_pb2.ProcessExit(
        component_id=proc.component_id,
        pid=proc.process.pid,
        exit_code=code if code >= 0 else 0,
        signal=-code if code < 0 else 0,
        killed=proc.process.killed,
        reason=proc.stop_reason or "exited",
    )


class ProcessTable:
    """Sessions by system, processes by (system, component id)."""

    def __init__(self, root: Path, log_dir: Path) -> None:
        self.root = root
        self.log_dir = log_dir
        self._token_dir: Path | None = None
        self.sessions: dict[str, SystemSession] = {}
        self.processes: dict[tuple[str, str], AgentProcess] = {}
        self._meter = ResourceMeter()
        self._tasks: set[asyncio.Task[None]] = set()

    @property
    def token_dir(self) -> Path:
        """The private directory of the token files this agent writes, made when the first one is.

        Tokens are credentials: a directory of this agent's own, not the logs'
        (removed when the agent stops). Made only when needed, so that an agent
        that never writes a token, or is killed, leaves no empty directory behind.
        """
        if self._token_dir is None:
            self._token_dir = Path(tempfile.mkdtemp(prefix="cast-agent-tokens-"))
        return self._token_dir

    # --------------------------------------------------------------- sessions

    def open_session(self, system: str, lease_ms: int, grace_ms: int) -> tuple[SystemSession, bool]:
        """The live session of ``system`` (resumed: True) or a new one.

        A session the reaper has not ended yet is still live, even a few
        milliseconds past its lease: resuming it keeps its processes reachable.
        """
        session = self.sessions.get(system)
        if session is not None and not session.ended:
            return session, True
        session = self.sessions[system] = SystemSession(system, lease_ms, grace_ms)
        return session, False

    def session(self, system: str) -> SystemSession:
        """The live session of ``system``; FAILED_PRECONDITION if it has none."""
        session = self.sessions.get(system)
        if session is None or session.ended:
            raise LockedError(f"system '{system}' has no session on this agent: Attach first (the agent starts "
                              "processes only for an attached orchestrator, so that none outlives it)")
        return session

    def running(self, system: str) -> list[agent_pb2.ProcessInfo]:
        """The running processes of ``system``."""
        return [agent_pb2.ProcessInfo(component_id=p.component_id, pid=p.process.pid)
                for (sys_name, _), p in self.processes.items() if sys_name == system and p.process.running]

    # -------------------------------------------------------------- processes

    async def launch(self, system: str, plan: LaunchPlan,
                     first_line: asyncio.Future[str] | None = None) -> AgentProcess:
        """Start ``plan`` for ``system``; ALREADY_EXISTS if that component runs, OSError if it cannot be run."""
        session = self.session(system)
        key = (system, plan.process_id)
        if key in self.processes:
            raise AlreadyExistsError(f"component '{plan.process_id}' of system '{system}' is running here "
                                     f"(pid {self.processes[key].process.pid}): Stop it first")

        def line(component_id: str, text: str) -> None:
            output = agent_pb2.OutputLine(component_id=component_id, stream=agent_pb2.OUTPUT_STREAM_STDOUT,
                                          text=text, pid=process.pid)
            if first_line is not None and not first_line.done():
                first_line.set_result(text)
            session.push(agent_pb2.AgentEvent(output=output))

        log_path = self.log_dir / _safe(system) / f"{_safe(plan.process_id)}.log"
        # The launchers' "no directory" means the orchestrator's; here that is the root (same checkout).
        env, token_file = plan.env, None
        if plan.token_file:
            token_file = self.token_dir / _safe(system) / f"{_safe(plan.process_id)}.token"
            write_token_file(token_file, env.get("CAST_TOKEN", ""))
            env = {**env, "CAST_TOKEN_FILE": str(token_file)}
        process = ComponentProcess(plan.process_id, plan.argv, env, log_path, line, plan.cwd or self.root,
                                   plan.dump_signal)
        try:
            await process.start()
        except OSError:
            if token_file is not None:
                token_file.unlink(missing_ok=True)
            raise
        proc = self.processes[key] = AgentProcess(system, process, token_file=token_file)
        self._spawn(self._watch(session, proc))
        log.info("system '%s': started %s (pid %d): %s", system, proc.component_id, process.pid, " ".join(plan.argv))
        return proc

    async def _watch(self, session: SystemSession, proc: AgentProcess) -> None:
        code = await proc.process.wait()
        proc.exit = _exit_of(proc, code)
        self._meter.forget(proc.process.pid)
        if self.processes.get((proc.system, proc.component_id)) is proc:
            del self.processes[(proc.system, proc.component_id)]
        if proc.token_file is not None:
            proc.token_file.unlink(missing_ok=True)  # no process reads it any more
        if not session.ended:
            session.push(agent_pb2.AgentEvent(exit=proc.exit))
        proc.done.set()
        log.info("system '%s': %s (pid %d) ended: %s", proc.system, proc.component_id, proc.process.pid,
                 str(proc.exit).replace("\n", " "))

    def renew(self, system: str, component_id: str, token: str) -> None:
        """Rewrite the token file of a running process (launched with token_file)."""
        self.session(system)
        proc = self.processes.get((system, component_id))
        if proc is None:
            raise NotFoundError(f"no process of component '{component_id}' of system '{system}' runs on this agent")
        if proc.token_file is None:
            raise LockedError(f"component '{component_id}' of system '{system}' was launched without token_file: "
                              "it reads no token file to renew (its token does not expire)")
        write_token_file(proc.token_file, token)

    async def stop(self, system: str, component_id: str, timeout_s: float, reason: str) -> agent_pb2.ProcessExit:
        """SIGTERM the component's group, SIGKILL after ``timeout_s``; its exit."""
        proc = self.processes.get((system, component_id))
        if proc is None:
            raise NotFoundError(f"no process of component '{component_id}' of system '{system}' runs on this agent")
        await self._stop(proc, timeout_s, reason)
        assert proc.exit is not None
        return proc.exit

    async def _stop(self, proc: AgentProcess, timeout_s: float, reason: str) -> None:
        if not proc.stop_reason:
            proc.stop_reason = reason
        await proc.process.stop(timeout_s)
        await proc.done.wait()

    async def end_session(self, session: SystemSession, reason: str) -> None:
        """Stop every process of the session's system (all at once, each with the session's grace), then end it."""
        procs = [p for (system, _), p in list(self.processes.items()) if system == session.system]
        if procs:
            log.warning("system '%s': %s; stopping %d process(es)", session.system, reason, len(procs))
        await asyncio.gather(*(self._stop(p, session.grace_s, reason) for p in procs))
        session.end()
        if self.sessions.get(session.system) is session:
            del self.sessions[session.system]

    # ---------------------------------------------------------- housekeeping

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def reap_forever(self, period_s: float = 0.05) -> None:
        """End every session whose lease ran out (the orchestrator went away and did not come back)."""
        ending: set[str] = set()
        while True:
            await asyncio.sleep(period_s)
            for session in list(self.sessions.values()):
                if session.expired and not session.ended and session.system not in ending:
                    ending.add(session.system)
                    session.end()  # no stream may resume it now; its processes go next

                    async def finish(s: SystemSession = session) -> None:
                        try:
                            await self.end_session(s, "lease expired")
                        finally:
                            ending.discard(s.system)

                    self._spawn(finish())

    async def sample_forever(self) -> None:
        """About every second, a resource sample of each process of each attached system."""
        while True:
            await asyncio.sleep(SAMPLE_PERIOD_S)
            for (system, _), proc in list(self.processes.items()):
                session = self.sessions.get(system)
                if session is None or not session.attached or not proc.process.running:
                    continue
                sample = self._meter.sample(proc.process.pid)
                if sample is not None:
                    session.push(agent_pb2.AgentEvent(resources=agent_pb2.ResourceSample(
                        component_id=proc.component_id, pid=proc.process.pid, cpu_percent=sample[0],
                        rss_bytes=sample[1])))

    async def stop_everything(self, reason: str) -> None:
        """Stop the processes of every system (the agent is stopping)."""
        await asyncio.gather(*(self.end_session(s, reason) for s in list(self.sessions.values())))
        for proc in list(self.processes.values()):  # a system whose session already ended
            await self._stop(proc, 3.0, reason)
        for task in list(self._tasks):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self._token_dir is not None:
            shutil.rmtree(self._token_dir, ignore_errors=True)

    def kill_everything(self) -> None:
        """SIGKILL every process group now (last resort on the way out)."""
        for proc in self.processes.values():
            proc.process.kill()


def _safe(name: str) -> str:
    """A name usable as one path component."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "_"
