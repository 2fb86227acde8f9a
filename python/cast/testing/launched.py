"""A whole system for a test, as ``cast run`` runs it: its servers and every component it launches.

:func:`run_system` gives a :class:`RunningSystem`, a :class:`cast.testing.LocalSystem`
with the run's own lines, its ``system.json`` and the ``cast`` tools aimed at it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cast.testing.servers import RunProcess
from cast.testing.system import LocalSystem, _config_file, _directory
from cast.testing.waiting import DEFAULT_TIMEOUT_S

__all__ = ["RunningSystem", "run_system"]


def run_system(
    config: str | os.PathLike[str] | Mapping[str, Any], *run_args: str, env: Mapping[str, str] | None = None,
    cwd: str | os.PathLike[str] | None = None, until: str = "components started in",
    timeout: float = 90.0, directory: str | os.PathLike[str] | None = None,
    runtime_dir: str | os.PathLike[str] | None = None,
) -> RunningSystem:
    """Run a whole system with ``cast run CONFIG --no-status``: its servers and every component it launches.

    Waits until ``cast run`` prints ``until`` (by default the line saying every
    component started). The runtime directory is the system's own, so the
    ``cast`` tools reach it through :meth:`RunningSystem.cli`.

    Args:
        config: the configuration's YAML file, or the same as a dict.
        run_args: more arguments of ``cast run`` (``--set``, ``--for``, ...).
        env: more environment for ``cast run`` (its own ``CAST_*`` variables
            are not passed on: the orchestrator gives components their identity).
        cwd: its working directory (default: the configuration's directory).
        until: the line that says it is up.
        timeout: seconds to wait for that line.
        directory: where its files go (default: a temporary directory, removed when closed).
        runtime_dir: the runtime directory (default: ``runtime`` in ``directory``).

    """
    where, own = _directory(directory)
    try:
        path = _config_file(config, None, where)
        runtime = Path(runtime_dir) if runtime_dir is not None else where / "runtime"
        server = RunProcess(path, runtime, run_args, env, Path(cwd) if cwd is not None else None, until, timeout)
    except BaseException:
        if own:
            shutil.rmtree(where, ignore_errors=True)
        raise
    return RunningSystem(server, server.secret(), server.system_name, server.subarchitectures, where, own, runtime)


class RunningSystem(LocalSystem):
    """A system ``cast run`` runs (:func:`run_system`): a :class:`LocalSystem`, and the run's own lines and tools."""

    _server: RunProcess

    @property
    def lines(self) -> list[str]:
        """The lines `cast run` printed so far, its components' included (the list grows while it runs)."""
        return self._server.lines

    def wait_for_line(self, text: str, timeout: float = DEFAULT_TIMEOUT_S, start: int = 0) -> str:
        """The first line `cast run` printed (from line ``start`` on) that contains ``text``."""
        line = self._server.wait_for_line(text, timeout, start)
        if line is None:
            raise AssertionError(f"`cast run` printed no line with {text!r} within {timeout:g} s; it printed:\n"
                                 f"{self.output()}")
        return line

    @property
    def process(self) -> subprocess.Popen[str]:
        """The `cast run` process."""
        return self._server.process

    @property
    def cwd(self) -> Path:
        """Where :meth:`cli` runs the tools: the working directory of `cast run`, unless set."""
        return self._server.cwd

    @cwd.setter
    def cwd(self, path: Path) -> None:
        self._server.cwd = Path(path)

    def state(self) -> dict[str, Any]:
        """The running system's ``system.json`` (its endpoint, servers, configuration, pid)."""
        return self._server.state()

    def cli_environment(self) -> dict[str, str]:
        """The environment that aims the ``cast`` tools at this run: this process's, with its runtime directory."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        env["CAST_RUNTIME_DIR"] = str(self.runtime_dir)
        return env

    def cli(self, *args: str, check: bool = True, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        """A ``cast`` command run against this system (in :attr:`cwd`); with ``check``, it must succeed."""
        done = subprocess.run([sys.executable, "-m", "cast.cli", *args], env=self.cli_environment(),
                              capture_output=True, text=True, timeout=timeout, cwd=self.cwd)
        if check and done.returncode != 0:
            raise AssertionError(f"cast {' '.join(args)} exited {done.returncode}:\n{done.stdout}{done.stderr}")
        return done

    def cli_json(self, *args: str) -> Any:
        """A ``cast`` command's ``--json`` output, parsed (it must succeed)."""
        return json.loads(self.cli(*args, "--json").stdout)

    _stop_signal = signal.SIGTERM
    _stop_timeout = 60.0

    def _stop_server(self) -> int:
        return self._server.stop(self._stop_signal, self._stop_timeout)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60.0) -> int:
        """Stop what the test started, then `cast run` with ``sig`` (SIGTERM; SIGINT as Ctrl-C); its exit status."""
        if not self._closed:
            self._stop_signal, self._stop_timeout = signal.Signals(sig), timeout
        return self.close()
