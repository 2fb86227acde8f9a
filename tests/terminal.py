"""A command run in a terminal window that the test then closes.

The command gets a pty as its standard streams and as the controlling terminal of a session of its
own, as a shell in a window gives it; closing the pty's other end is closing the window: the kernel
sends the command SIGHUP, and its writes to the terminal fail from then on.
"""

from __future__ import annotations

import os
import pty
import select
import subprocess
import sys
import time
from pathlib import Path

# Runs in the new session before the command: makes the pty (its stdin) the controlling terminal, then
# becomes the command (same process, so the command is the session's leader and gets the SIGHUP).
_TAKE_TTY = ("import fcntl, os, sys, termios; fcntl.ioctl(0, termios.TIOCSCTTY, 0); "
             "os.execv(sys.argv[1], sys.argv[1:])")


class Terminal:
    """``argv`` running in a terminal window of its own (``argv[0]`` is a path)."""

    def __init__(self, argv: list[str], env: dict[str, str] | None = None, cwd: Path | None = None) -> None:
        self._window, tty = pty.openpty()
        self.proc = subprocess.Popen([sys.executable, "-c", _TAKE_TTY, *argv], stdin=tty, stdout=tty, stderr=tty,
                                     start_new_session=True, env=env, cwd=cwd)
        os.close(tty)
        self.shown = b""
        self._open = True

    def wait_for(self, text: str, timeout: float = 60.0) -> None:
        """Read what the window shows until ``text`` appears."""
        deadline = time.monotonic() + timeout
        while text.encode() not in self.shown:
            assert time.monotonic() < deadline and self.proc.poll() is None, \
                f"{text!r} not shown (exit {self.proc.poll()}): {self.shown.decode(errors='replace')}"
            if select.select([self._window], [], [], 0.5)[0]:
                self.shown += os.read(self._window, 65536)

    def type(self, line: str) -> None:
        """Type ``line`` and Enter into the window (to a shell running there)."""
        os.write(self._window, f"{line}\n".encode())

    def close(self) -> None:
        """Close the window (the command gets SIGHUP; a shell there sends its jobs one more)."""
        if self._open:
            self._open = False
            os.close(self._window)

    def end(self) -> None:
        """Close the window and make sure the command is gone (a test's clean-up)."""
        self.close()
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
