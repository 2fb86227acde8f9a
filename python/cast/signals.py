"""Signals of our processes: SIGINT/SIGTERM/SIGHUP end a long-running command; SIGQUIT prints every thread's stack.

SIGHUP is a terminal that went away (its window closed): a command then stops as
on SIGTERM, finishing what it writes (a journal, a recording), with standard
output and error pointed at /dev/null first, since the terminal refuses writes.
A line written after the window closed and before the SIGHUP is handled meets
the same refusal (EIO): :func:`say` writes a command's lines so that it is the
terminal's silence, not the command's end.

SIGQUIT is the JVM's habit (a thread dump, and the process goes on), which
Python's :mod:`faulthandler` gives too: a component or ``cast`` command that
hangs says where with ``kill -QUIT PID``, and the orchestrator and the agent
send it to a component that did not stop in time before they kill it, so its
log shows what it was stuck in (cast.orchestrator.process).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import faulthandler
import os
import signal
import sys
import threading
from collections.abc import Iterable
from typing import TextIO

__all__ = ["STACK_DUMP_SIGNAL", "descriptors_on", "dump_stacks_on_sigquit", "say", "silence", "terminal_descriptors",
           "terminate_when_stdin_closes", "termination"]

STACK_DUMP_SIGNAL = signal.SIGQUIT
"""The signal on which a Python or Java process of ours prints every thread's stack and carries on."""


def dump_stacks_on_sigquit() -> None:
    """From now on SIGQUIT prints every thread's stack to stderr, and the process carries on.

    faulthandler writes from the signal handler itself, without the GIL, so the
    stacks come out even when the process is stuck holding it.
    """
    with contextlib.suppress(AttributeError, ValueError, OSError, RuntimeError):
        # No SIGQUIT (Windows), or stderr is not a real file (an embedding host): no dumps, nothing else changes.
        faulthandler.register(STACK_DUMP_SIGNAL, file=sys.stderr, all_threads=True, chain=False)


def terminal_descriptors() -> list[int]:
    """Standard output and error, those of them that are a terminal (ask before it hangs up: then asking fails)."""
    return [fd for fd in (1, 2) if os.isatty(fd)]


def silence(descriptors: Iterable[int]) -> None:
    """Point each descriptor at /dev/null: its terminal is gone.

    Neither what is written to it from now on nor what Python still buffers for it (flushed at exit)
    may fail then.
    """
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in descriptors:
            with contextlib.suppress(OSError):
                os.dup2(devnull, fd)
    finally:
        os.close(devnull)


def say(line: str, to: TextIO | None = None) -> None:
    """Write ``line`` and a newline to ``to`` (standard output by default) in one write, flushed.

    One write, so that a reader waiting for the line (a test, a parent process) sees it whole or not
    at all, even with ``PYTHONUNBUFFERED`` (where ``print`` writes the text and its newline apart).
    A terminal that refuses it (EIO: its window closed, the SIGHUP not handled yet) is pointed at
    /dev/null with standard output and error when they are that terminal, and the line is dropped: the
    SIGHUP that comes stops the command in order. Any other error is raised.
    """
    out = sys.stdout if to is None else to
    try:
        out.write(line + "\n")
        out.flush()
    except OSError as exc:
        if exc.errno != errno.EIO:
            raise
        silence(descriptors_on(os.fstat(out.fileno())))


def descriptors_on(file: os.stat_result, among: Iterable[int] = (1, 2)) -> list[int]:
    """Those of ``among`` (standard output and error by default) that are ``file``; a closed one is not."""
    found = []
    for fd in among:
        with contextlib.suppress(OSError):
            if os.path.samestat(os.fstat(fd), file):
                found.append(fd)
    return found


def termination() -> asyncio.Event:
    """An event set once SIGINT, SIGTERM or SIGHUP arrives, handled on the running event loop.

    The handlers are in place on return: a command that says it is up calls this first, so that a
    signal sent as soon as it says so stops it in order rather than by the signal's default action.
    """
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    terminals = terminal_descriptors()

    def hung_up() -> None:
        silence(terminals)
        stop.set()

    for sig, handler in ((signal.SIGINT, stop.set), (signal.SIGTERM, stop.set), (signal.SIGHUP, hung_up)):
        # Not available off the main thread or on some platforms: then only cancellation ends the wait.
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, handler)
    return stop


def terminate_when_stdin_closes() -> threading.Thread:
    """From now on, the end of standard input is a SIGTERM to this process (``--exit-with-stdin``).

    A process that starts ours with a pipe as its standard input keeps the other end open for as
    long as it lives; when it ends, however it ends (a failed test, a crash, SIGKILL), the kernel
    closes that end, our read sees the end of the file, and we stop as on SIGTERM: the clean
    shutdown. So a test kit leaves no server behind, even when its own process is killed.
    Whatever arrives on standard input before its end is read and ignored.
    """

    def watch() -> None:
        with contextlib.suppress(OSError):
            while os.read(0, 4096):
                pass
        os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=watch, name="cast-stdin-lifeline", daemon=True)
    thread.start()
    return thread
