"""The servers behind a test's system: in the test's process, ``cast serve`` or ``cast run`` as a process.

Each serves on a port of 127.0.0.1 the kernel picks, signs tokens with a secret
made for the test, and is stopped by :meth:`stop`. The two processes are
started with ``--exit-with-stdin`` and a pipe as their standard input, whose
other end only this process holds: when it ends, however it ends, they stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from cast.config import SystemConfig
from cast.errors import InvalidArgumentError, UnavailableError

if TYPE_CHECKING:
    from cast.core.system import System
    from cast.server.app import RunningServer

__all__ = ["InProcessServer", "RunProcess", "Server", "ServeProcess"]

LISTEN = "127.0.0.1:0"
START_TIMEOUT_S = 90.0
"""How long a process may take to say it listens (a busy 2-core machine starts Python slowly)."""
STOP_TIMEOUT_S = 30.0


class Server(Protocol):
    """What :class:`cast.testing.LocalSystem` needs of the server it tests against."""

    endpoint: str

    def output(self) -> str:
        """What the server printed or logged so far."""

    def stop(self) -> int:
        """Stop cleanly; the exit status (0 in process)."""

    def kill(self) -> None:
        """Stop at once, as a crash would: clients see their connections break."""

    def restart(self) -> None:
        """A new server with empty memories on the same address (killing the old one first)."""


class _Lines:
    """The lines a process prints, collected by a thread; waits for a line that contains a text."""

    def __init__(self, process: subprocess.Popen[str]) -> None:
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self._ended = False
        self._thread = threading.Thread(target=self._pump, args=(process,), daemon=True, name="cast-testing-output")
        self._thread.start()

    def _pump(self, process: subprocess.Popen[str]) -> None:
        assert process.stdout is not None
        for line in process.stdout:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self._ended = True
            self._changed.notify_all()

    def wait_for(self, text: str, timeout: float, start: int = 0) -> str | None:
        """The first line from ``start`` on that contains ``text``; None if the output ended or time ran out."""
        def found() -> str | None:
            return next((line for line in self.lines[start:] if text in line), None)

        with self._changed:
            self._changed.wait_for(lambda: found() is not None or self._ended, timeout)
            return found()

    def text(self) -> str:
        """Everything printed so far."""
        with self._changed:
            return "".join(self.lines)

    def join(self, timeout: float) -> None:
        """Wait until the output ended (after the process did)."""
        self._thread.join(timeout)


def _child_env(extra: Mapping[str, str] | None) -> dict[str, str]:
    """This process's environment without the launch contract of a component (the server is not one)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    env.update(extra or {})
    return env


def _end(process: subprocess.Popen[str], sig: int, timeout: float) -> int:
    """Send ``sig`` (if it still runs) and wait; SIGKILL after ``timeout``; the exit status."""
    if process.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            process.send_signal(sig)
    try:
        return process.wait(timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise AssertionError(f"the system's process (pid {process.pid}) did not stop within {timeout:g} s of "
                             f"signal {signal.Signals(sig).name}; it was killed") from None
    finally:
        if process.stdin is not None:
            with contextlib.suppress(OSError):
                process.stdin.close()


class ServeProcess:
    """``cast serve CONFIG`` as a process of the test."""

    def __init__(self, config: Path, secret_file: Path, workdir: Path, serve_args: Sequence[str] = ()) -> None:
        self._argv = [sys.executable, "-m", "cast.cli", "serve", str(config), "--secret-file", str(secret_file),
                      "--exit-with-stdin", *serve_args]
        self._workdir = workdir
        self._earlier = ""  # the output of servers this one replaced (restart)
        self.endpoint = ""
        self._start(LISTEN)

    def _start(self, listen: str) -> None:
        self.process = subprocess.Popen(
            [*self._argv, "--listen", listen], cwd=self._workdir, env=_child_env(None), stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        self._lines = _Lines(self.process)
        line = self._lines.wait_for("listening on ", START_TIMEOUT_S)
        if line is None:
            _end(self.process, signal.SIGKILL, STOP_TIMEOUT_S)
            self._lines.join(5)
            raise UnavailableError(f"`cast serve` did not start (command: {' '.join(self._argv)}); it printed:\n"
                                   f"{self._lines.text()}")
        self.endpoint = line.strip().removeprefix("listening on ")

    def output(self) -> str:
        """What the server printed (the servers it replaced first)."""
        return self._earlier + self._lines.text()

    def stop(self) -> int:
        """SIGTERM: the clean shutdown; its exit status."""
        code = _end(self.process, signal.SIGTERM, STOP_TIMEOUT_S)
        self._lines.join(5)
        return code

    def kill(self) -> None:
        """SIGKILL: gone at once."""
        _end(self.process, signal.SIGKILL, STOP_TIMEOUT_S)
        self._lines.join(5)

    def restart(self) -> None:
        """A new `cast serve` on the same address."""
        self.kill()
        self._earlier = self.output()
        self._start(self.endpoint)


class RunProcess:
    """``cast run CONFIG`` as a process of the test: the whole system, its components launched."""

    def __init__(
        self, config: Path, runtime_dir: Path, run_args: Sequence[str] = (), env: Mapping[str, str] | None = None,
        cwd: Path | None = None, until: str = "components started in", timeout: float = START_TIMEOUT_S,
    ) -> None:
        self.runtime_dir = runtime_dir
        self.cwd = cwd or config.parent
        argv = [sys.executable, "-m", "cast.cli", "run", str(config), "--no-status", "--runtime-dir",
                str(runtime_dir), "--exit-with-stdin", *run_args]
        self.process = subprocess.Popen(argv, cwd=self.cwd, env=_child_env(env), stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._lines = _Lines(self.process)
        if self._lines.wait_for(until, timeout) is None or self.process.poll() is not None:
            _end(self.process, signal.SIGKILL, STOP_TIMEOUT_S)
            self._lines.join(5)
            raise UnavailableError(f"`cast run {config}` did not print '{until}' within {timeout:g} s; it printed:\n"
                                   f"{self._lines.text()}")
        state = self.state()
        self.endpoint = str(state["endpoint"])
        self.subarchitectures = [str(sa) for server in state.get("servers", {}).values()
                                 for sa in server.get("subarchitectures", [])]
        self.system_name = str(state.get("system", ""))

    def state(self) -> dict[str, Any]:
        """The running system's ``system.json``."""
        try:
            return dict(json.loads((self.runtime_dir / "system.json").read_text()))
        except (OSError, ValueError) as exc:
            raise UnavailableError(f"`cast run` wrote no readable {self.runtime_dir / 'system.json'} ({exc}); "
                                   f"it printed:\n{self._lines.text()}") from None

    def secret(self) -> bytes:
        """The secret `cast run` made for the run."""
        return (self.runtime_dir / "secret").read_bytes().strip()

    @property
    def lines(self) -> list[str]:
        """The lines `cast run` printed so far (the list grows while it runs)."""
        return self._lines.lines

    def wait_for_line(self, text: str, timeout: float, start: int = 0) -> str | None:
        """The first line (from line ``start``) that contains ``text``, waiting up to ``timeout`` seconds."""
        return self._lines.wait_for(text, timeout, start)

    def output(self) -> str:
        """What `cast run` printed so far (its own lines and its components')."""
        return self._lines.text()

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60.0) -> int:
        """Signal `cast run` (SIGTERM, or SIGINT as Ctrl-C) and wait for it to stop its components; its status."""
        code = _end(self.process, sig, timeout)
        self._lines.join(5)
        return code

    def kill(self) -> None:
        """SIGKILL `cast run`; its components get SIGTERM from the kernel when it dies (cast.orchestrator)."""
        _end(self.process, signal.SIGKILL, STOP_TIMEOUT_S)
        self._lines.join(5)

    def restart(self) -> None:
        """Not offered: `cast run` restarts components itself, by their restart policies."""
        raise InvalidArgumentError("restart() restarts a served system (start_system); a system run with `cast run` "
                                   "is stopped with stop() and run again with run_system()")


class _LogLines(logging.Handler):
    """The records of the server's loggers, kept as lines for :meth:`InProcessServer.output`."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record) + "\n")


class InProcessServer:
    """The server in the test's own process: its gRPC server on an event loop of its own thread.

    The same server as ``cast serve`` (:func:`cast.server.app.start_server` over
    :func:`cast.server.app.system_from_config`, the configuration's in-process
    components started), so the same rulebook; only the process is shared.
    """

    def __init__(self, config: SystemConfig, secret: bytes) -> None:
        from cast.auth import TokenSigner

        self.config = config
        self._signer = TokenSigner(secret)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True, name="cast-testing-server")
        self._thread.start()
        self._log = _LogLines()
        self._logger = logging.getLogger("cast")
        self._logger.addHandler(self._log)
        self._added_paths = [str(p) for p in config.python_path if str(p) not in sys.path]
        sys.path[:0] = self._added_paths  # in-process components and policies import from there, as in cast serve
        self.endpoint = ""
        self._running: RunningServer | None = None
        try:
            self._start(LISTEN)
        except BaseException:
            self._close_loop()
            raise

    def _start(self, listen: str) -> None:
        from cast.server.app import settings_from_config, start_server, system_from_config
        from cast.server.in_process import InProcessComponents

        system = system_from_config(self.config)
        started = asyncio.run_coroutine_threadsafe(
            start_server(system, self._signer, listen, settings_from_config(self.config)), self._loop)
        try:
            running = started.result(START_TIMEOUT_S)
        except BaseException:
            system.close()
            raise
        components = InProcessComponents(system)
        for comp in self.config.components:
            if comp.in_process:
                components.start(comp)
        running.on_stop(components.stop_all)
        self._running = running
        self.endpoint = running.endpoint

    @property
    def core(self) -> System:
        """The server's :class:`cast.core.system.System`, for white-box checks."""
        assert self._running is not None
        return self._running.system

    def output(self) -> str:
        """What the server logged (level INFO and up) while it ran."""
        return "".join(self._log.lines)

    def _stop_running(self, grace: float) -> None:
        running, self._running = self._running, None
        if running is not None:
            asyncio.run_coroutine_threadsafe(running.stop(grace), self._loop).result(STOP_TIMEOUT_S)

    def stop(self) -> int:
        """Stop in-process components, then the server, letting calls finish for a second."""
        try:
            self._stop_running(1.0)
        finally:
            self._close_loop()
        return 0

    def kill(self) -> None:
        """Stop serving at once: connections break, no call is let finish."""
        self._stop_running(0.0)

    def restart(self) -> None:
        """A new server with empty memories on the same address."""
        self.kill()
        self._start(self.endpoint)

    def _close_loop(self) -> None:
        if self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(STOP_TIMEOUT_S)
        self._loop.close()
        self._logger.removeHandler(self._log)
        for path in self._added_paths:
            with contextlib.suppress(ValueError):
                sys.path.remove(path)
