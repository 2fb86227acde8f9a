"""Supervision of launched components: start, watch, restart by policy, stop in order.

A component that exits while the system runs is a crash if its exit code is
not 0. Its restart policy decides what follows: ``never`` leaves it down,
``on-failure`` restarts crashes, ``always`` restarts any exit; each restart
waits ``backoff`` seconds, doubling, and gives up after ``max_restarts``. Exit
code 2 is the runners' "cannot start" (class not found, launch environment
missing): never restarted, since trying again cannot help. The
server has already released the crashed component's locks and tasks (its
session ended with its connection), and a restarted component registering
again ends any session of the old one that is still open.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from cast.config.model import ComponentConfig, SystemConfig
from cast.errors import CastError
from cast.orchestrator.launchers import launcher_for, stack_dump_signal
from cast.orchestrator.process import ComponentProcess, LineSink
from cast.orchestrator.remote import Agents, RemoteProcess

__all__ = ["Phase", "Supervised", "Supervisor"]


class Phase(enum.Enum):
    """Where a supervised component is, as the orchestrator sees it."""

    PENDING = "pending"
    RUNNING = "running"
    RESTARTING = "restarting"
    EXITED = "exited"  # ended with code 0 and is not restarted
    FAILED = "failed"  # crashed and is not restarted (policy, or out of restarts)
    STOPPING = "stopping"
    STOPPED = "stopped"


@dataclass
class Supervised:
    """One launched component and its history."""

    config: ComponentConfig
    phase: Phase = Phase.PENDING
    process: ComponentProcess | RemoteProcess | None = None
    restarts: int = 0
    crashes: list[int] = field(default_factory=list)  # exit codes of unexpected exits
    stop_code: int | None = None  # exit code when the orchestrator stopped it
    error: str = ""
    started_at: float = 0.0
    host_losses: int = 0  # times it ended because its host was lost (not counted as crashes)

    @property
    def pid(self) -> int:
        """The current process id (0 if none)."""
        return self.process.pid if self.process is not None and self.process.running else 0

    @property
    def failed(self) -> bool:
        """Whether this component counts as a failure of the run."""
        return (bool(self.crashes) or self.phase is Phase.FAILED or bool(self.host_losses)
                or (self.stop_code not in (None, 0)))


Notify = Callable[[str], None]

CANNOT_START = 2
"""Exit code of every language's runner when the component cannot start at all (class, environment)."""


class Supervisor:
    """Launches and supervises every launched component of a system."""

    def __init__(
        self,
        config: SystemConfig,
        contract: Callable[[ComponentConfig], dict[str, str]],
        logs: Path,
        sink: LineSink,
        notify: Notify,
        env: Mapping[str, str] | None = None,
        agents: Agents | None = None,
    ) -> None:
        self.config = config
        self._agents = agents  # components on other hosts are launched through their agents
        self._contract = contract
        self._logs = logs
        self._sink = sink
        self._notify = notify
        self._env = dict(os.environ if env is None else env)
        self.components: dict[str, Supervised] = {c.id: Supervised(c) for c in config.components if c.launched}
        self._tasks: dict[str, asyncio.Task[None]] = {}
        self._stopping = False

    def runs(self, component_id: str, *, steady: bool = False) -> bool:
        """Whether the component's process runs (its token is worth renewing); ``steady``: and no stop began."""
        sup = self.components.get(component_id)
        if sup is None or sup.process is None or not sup.process.running:
            return False
        return sup.phase is Phase.RUNNING or not steady

    def start_all(self) -> None:
        """Launch every component (they connect concurrently)."""
        for sup in self.components.values():
            self._tasks[sup.config.id] = asyncio.ensure_future(self._supervise(sup))

    async def _launch(self, sup: Supervised) -> bool:
        comp = sup.config
        if comp.remote:
            return await self._launch_remote(sup)
        launcher = launcher_for(comp.language)
        try:
            argv = launcher.command(comp, self.config, self._env)
        except CastError as exc:
            sup.error = exc.message
            return False
        env = {**self._env, **launcher.environment(comp, self.config, self._env), **self._contract(comp)}
        process = ComponentProcess(comp.id, argv, env, self._logs / f"{comp.id}.log", self._sink,
                                   launcher.working_directory(comp), stack_dump_signal(launcher))
        try:
            await process.start()
        except OSError as exc:
            sup.error = f"cannot start {argv[0]}: {exc.strerror or exc}"
            return False
        sup.process, sup.phase, sup.started_at = process, Phase.RUNNING, time.monotonic()
        return True

    async def _launch_remote(self, sup: Supervised) -> bool:
        """Launch through the agent of the component's host: the same contract, output and exits come back."""
        comp = sup.config
        assert self._agents is not None, f"{comp.id} runs on host '{comp.host}' but no agent is attached"
        process = self._agents.process(comp, self._contract(comp), self._logs / f"{comp.id}.log", self._sink)
        try:
            await process.start()
        except CastError as exc:
            sup.error = exc.message
            return False
        sup.process, sup.phase, sup.started_at = process, Phase.RUNNING, time.monotonic()
        return True

    async def _supervise(self, sup: Supervised) -> None:
        comp = sup.config
        while not self._stopping:
            if not await self._launch(sup):
                sup.phase = Phase.FAILED
                self._notify(f"{comp.id}: {sup.error}")
                return
            assert sup.process is not None
            if self._stopping:  # a stop began while this (re)start was under way
                return
            code = await sup.process.wait()
            if self._stopping:
                return
            if isinstance(sup.process, RemoteProcess) and sup.process.host_lost:
                if not await self._host_lost(sup, sup.process):
                    return
                continue
            if code != 0:
                sup.crashes.append(code)
            how = f"crashed (exit code {code})" if code != 0 else "exited"
            if code == CANNOT_START:
                # The runners' "bad class or launch environment": starting again cannot help.
                sup.phase = Phase.FAILED
                self._notify(f"{comp.id} could not start (exit code {code}: see its output or "
                             f"{self._logs / (comp.id + '.log')}); not restarted")
                return
            if not comp.restart.should_restart(code, sup.restarts):
                sup.phase = Phase.FAILED if code != 0 else Phase.EXITED
                reason = "" if comp.restart.mode == "never" or code == 0 else f" after {sup.restarts} restarts"
                self._notify(f"{comp.id} {how}; not restarted{reason} (restart: {comp.restart.mode})")
                return
            delay = comp.restart.delay(sup.restarts)
            sup.phase = Phase.RESTARTING
            self._notify(f"{comp.id} {how}; restarting in {delay:.1f} s (restart {sup.restarts + 1} of "
                         f"{comp.restart.max_restarts})")
            await asyncio.sleep(delay)
            sup.restarts += 1

    async def _host_lost(self, sup: Supervised, process: RemoteProcess) -> bool:
        """Its host was lost: failed, and no restart until the host is back; then whether to restart it.

        The link already said so on one line naming the host and its components. Trying to launch
        on a host that does not answer cannot help, so the component waits (FAILED) for the link to
        attach again; then its restart policy decides, as after a crash.
        """
        comp = sup.config
        sup.host_losses += 1
        sup.phase, sup.error = Phase.FAILED, f"host '{comp.host}' lost"
        if not comp.restart.should_restart(-9, sup.restarts):
            reason = "" if comp.restart.mode == "never" else f" after {sup.restarts} restarts"
            self._notify(f"{comp.id}: host '{comp.host}' lost; not restarted{reason} (restart: {comp.restart.mode})")
            return False
        await process.link.back.wait()
        delay = comp.restart.delay(sup.restarts)
        sup.phase = Phase.RESTARTING
        self._notify(f"{comp.id}: host '{comp.host}' is back; restarting in {delay:.1f} s (restart "
                     f"{sup.restarts + 1} of {comp.restart.max_restarts})")
        await asyncio.sleep(delay)
        sup.restarts += 1
        return True

    async def stop_all(self, timeout: float) -> None:
        """Stop components in reverse start order: SIGTERM, then SIGKILL after ``timeout`` seconds."""
        self._stopping = True
        for sup in reversed(list(self.components.values())):
            task = self._tasks.get(sup.config.id)
            # A second Ctrl-C may have killed it before its turn came: how it ended is still this stop's outcome.
            killed_early = sup.process is not None and sup.process.killed
            if sup.process is not None and (sup.process.running or killed_early):
                sup.phase = Phase.STOPPING
                sup.stop_code = await sup.process.stop(timeout)
                if killed_early:  # "stopping now: killing every component" said why
                    self._notify(f"{sup.config.id} killed before its turn to stop")
                elif sup.process.killed:
                    self._notify(f"{sup.config.id} did not stop within {timeout:.0f} s: killed"
                                 + (" (its threads' stacks are in its log)" if sup.process.dumped else ""))
                elif sup.stop_code != 0:
                    self._notify(f"{sup.config.id} stopped with exit code {sup.stop_code}")
                sup.phase = Phase.STOPPED
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        # A process (re)started while the others were being stopped: stop it too.
        for sup in self.components.values():
            if sup.process is not None and sup.process.running:
                sup.stop_code = await sup.process.stop(timeout)
                sup.phase = Phase.STOPPED

    def kill_all(self) -> None:
        """SIGKILL every running component at once (a second Ctrl-C: no more waiting)."""
        self._stopping = True
        for sup in self.components.values():
            if sup.process is not None and sup.process.running:
                sup.process.kill()
