"""One component process: started in its own process group, output to a log file, stopped in order.

Each process gets its own session (process group), so that a Ctrl-C in the
terminal reaches only the orchestrator, which then stops components in order,
and so that stopping a component also stops whatever it started. On Linux the
process also gets SIGTERM if the orchestrator dies, so nothing is left behind
even after a SIGKILL of the orchestrator.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

__all__ = ["DUMP_WAIT_S", "ComponentProcess", "LineSink"]

DUMP_WAIT_S = 1.0
"""How long a process that did not stop in time has to print its stacks before the SIGKILL."""

LineSink = Callable[[str, str], None]
"""Receives (component id, output line) for every line a component prints."""

# On Linux a component is started through this tiny trampoline, which asks the kernel to send it
# SIGTERM when the orchestrator dies and then execs the real command (same pid). It is not done
# with preexec_fn: Python code between fork and exec in a process with gRPC threads can crash the
# child (gRPC's fork handlers), and without preexec_fn the child is spawned without running any.
_TRAMPOLINE = (
    "import ctypes,os,signal,sys\n"
    "ctypes.CDLL(None).prctl(1, signal.SIGTERM)\n"
    "if os.getppid() != int(sys.argv[1]): os._exit(70)\n"
    "os.execvp(sys.argv[2], sys.argv[2:])\n"
)


def _with_trampoline(argv: Sequence[str]) -> list[str]:
    if not sys.platform.startswith("linux"):
        return list(argv)
    return [sys.executable, "-S", "-c", _TRAMPOLINE, str(os.getpid()), *argv]


class ComponentProcess:
    """A started component process."""

    def __init__(
        self,
        component_id: str,
        argv: Sequence[str],
        env: Mapping[str, str],
        log_path: Path,
        sink: LineSink,
        cwd: Path | None = None,
        dump_signal: int | None = None,
    ) -> None:
        self.component_id = component_id
        # Sent before the SIGKILL of a stop that timed out, when the process prints its threads' stacks on it
        # (Python's runner and `cast`, the JVM: SIGQUIT); None for one it would only kill (C++, other).
        self.dump_signal = dump_signal
        self.argv = list(argv)
        self.env = dict(env)
        self.log_path = log_path
        self.cwd = cwd
        self._sink = sink
        self._proc: asyncio.subprocess.Process | None = None
        self._pump: asyncio.Task[None] | None = None
        self.killed = False
        self.dumped = False  # asked for its stacks (dump_signal) before it was killed

    @property
    def pid(self) -> int:
        """The process id (0 before start)."""
        return self._proc.pid if self._proc is not None else 0

    @property
    def running(self) -> bool:
        """Whether the process has been started and has not exited."""
        return self._proc is not None and self._proc.returncode is None

    async def start(self) -> None:
        """Start the process; OSError if it cannot be executed."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._proc = await asyncio.create_subprocess_exec(
            *_with_trampoline(self.argv),
            env=self.env,
            cwd=self.cwd,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
            start_new_session=True,
        )
        self._pump = asyncio.ensure_future(self._read_output(self._proc))

    async def _read_output(self, proc: asyncio.subprocess.Process) -> None:
        assert proc.stdout is not None
        with self.log_path.open("ab") as log:
            while True:
                raw = await proc.stdout.readline()
                if not raw:
                    return
                log.write(raw)
                log.flush()
                self._sink(self.component_id, raw.decode(errors="replace").rstrip("\r\n"))

    async def wait(self) -> int:
        """Wait for the process to exit; return its exit code (negative: killed by that signal)."""
        assert self._proc is not None
        code = await self._proc.wait()
        if self._pump is not None:
            await self._pump
        self._kill_group(signal.SIGKILL)  # whatever the component started must not outlive it
        return code

    def _kill_group(self, sig: int) -> None:
        if self._proc is None:
            return
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self._proc.pid, sig)

    def kill(self) -> None:
        """SIGKILL the process group now."""
        self.killed = True
        self._kill_group(signal.SIGKILL)

    async def stop(self, timeout: float) -> int:
        """SIGTERM (the runner calls stop()), then SIGKILL after ``timeout`` seconds; return the exit code.

        Before the SIGKILL, a process with a ``dump_signal`` gets it, so that its log says where it was stuck.
        """
        assert self._proc is not None
        if self._proc.returncode is None:
            self._kill_group(signal.SIGTERM)
            try:
                return await asyncio.wait_for(asyncio.shield(self.wait()), timeout)
            except TimeoutError:
                self.killed = True
                await self._dump_stacks()
                self._kill_group(signal.SIGKILL)
        return await self.wait()

    async def _dump_stacks(self) -> None:
        """Ask a stuck process for its threads' stacks and give it a moment to write them to its log."""
        if self.dump_signal is None or self._proc is None or self._proc.returncode is not None:
            return
        try:
            os.kill(self._proc.pid, self.dump_signal)  # the process only: what it started is not ours to ask
        except (ProcessLookupError, PermissionError):
            return
        self.dumped = True
        # faulthandler writes at once; the JVM at its next safepoint. What is written is read from the pipe
        # even after the SIGKILL, so this waits only for the writing (or for an exit the dump let happen).
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(self._proc.wait()), DUMP_WAIT_S)
