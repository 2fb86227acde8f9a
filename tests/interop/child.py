"""A component process of another language, started by a test, whose output is collected as it comes.

The C++ and Java helpers (cpp_support.py, java_support.py) build on it: they differ only in the
command line and in what they do with each line the process prints.
"""

from __future__ import annotations

import signal
import subprocess
import threading


class ChildProcess:
    """A process started with the launch contract in ``env``; stdout and stderr kept for failure messages."""

    def __init__(self, name: str, argv: list[str], env: dict[str, str], stdin: bool) -> None:
        self.name = name
        self.stdout_lines: list[str] = []
        self.stderr_lines: list[str] = []
        self.proc = subprocess.Popen(
            argv,
            env=env,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            encoding="utf-8",
        )
        threading.Thread(target=self._read_stdout, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()

    def on_line(self, line: str) -> None:
        """Called on the reader thread with each stdout line (a subclass parses its protocol here)."""

    def on_end(self) -> None:
        """Called on the reader thread when stdout closes (the process exited)."""

    def _read_stdout(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.stdout_lines.append(line)
            self.on_line(line)
        self.on_end()

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr_lines.append(line)

    def output(self) -> str:
        """What the process printed, for failure messages."""
        return "".join(self.stdout_lines[-40:]) + "--- stderr ---\n" + "".join(self.stderr_lines[-60:])

    def wait(self, timeout: float = 30.0) -> int:
        """The exit status, waiting up to ``timeout`` seconds."""
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{self.name} did not exit within {timeout} s\n{self.output()}") from None

    def terminate(self) -> None:
        """SIGTERM: the runner calls stop() and exits."""
        self.proc.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        """SIGKILL: no clean-up at all; the server must notice the session end."""
        self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        """Kill the process if it is still running (test clean-up)."""
        if self.proc.poll() is None:
            self.kill()
