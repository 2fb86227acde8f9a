"""A command's lines: written whole in one write, and a terminal that hung up silenced rather than fatal."""

from __future__ import annotations

import contextlib
import io
import os
import sys
from pathlib import Path

import pytest

from cast.signals import say
from tests.terminal import Terminal


class _Writes(io.RawIOBase):
    """A raw stream that keeps each write it is given apart."""

    def __init__(self) -> None:
        self.writes: list[bytes] = []

    def writable(self) -> bool:
        return True

    def write(self, data: bytes) -> int:  # type: ignore[override]
        self.writes.append(bytes(data))
        return len(data)


def _unbuffered() -> tuple[io.TextIOWrapper, _Writes]:
    raw = _Writes()
    # What standard output is under PYTHONUNBUFFERED (and -u): no buffer, each write of the text layer goes down.
    return io.TextIOWrapper(raw, write_through=True), raw  # type: ignore[arg-type]


def test_a_line_is_one_write_even_unbuffered() -> None:
    out, raw = _unbuffered()
    print("listening on 127.0.0.1:1", file=out, flush=True)
    assert len(raw.writes) == 2, "print writes the text and its newline apart: a reader may see half a line"
    raw.writes.clear()
    say("listening on 127.0.0.1:1", out)
    assert raw.writes == [b"listening on 127.0.0.1:1\n"]


_AFTER_HANGUP = """
import os, signal, sys, time
from cast.signals import say
signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as a command before its handler stops it: the window's gone
say("up")
while not os.path.exists(sys.argv[1]):  # the test has closed the window: the terminal refuses writes (EIO)
    time.sleep(0.05)
say("written after the window closed")
print("and print after it", flush=True)
say("to standard error too", sys.stderr)
"""


def test_a_line_for_a_closed_window_silences_the_terminal_and_the_command_goes_on(tmp_path: Path) -> None:
    closed = tmp_path / "closed"
    window = Terminal([sys.executable, "-c", _AFTER_HANGUP, str(closed)],
                      env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    try:
        window.wait_for("up")
        window.close()
        closed.touch()
        # Without say()'s care the line fails with EIO (exit 1, its traceback lost with the window).
        assert window.proc.wait(timeout=60) == 0
    finally:
        window.end()


def test_other_errors_are_raised() -> None:
    read, write = os.pipe()
    os.close(read)
    out = os.fdopen(write, "w")
    try:
        with pytest.raises(BrokenPipeError):  # Python ignores SIGPIPE: the write fails with EPIPE
            say("nobody reads this", out)
    finally:
        with contextlib.suppress(BrokenPipeError):  # closing flushes the line still buffered: EPIPE again
            out.close()
