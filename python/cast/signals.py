"""Signals of our processes: SIGINT/SIGTERM end a long-running command; SIGQUIT prints every thread's stack.

SIGQUIT is the JVM's habit (a thread dump, and the process goes on), which
Python's :mod:`faulthandler` gives too: a component or ``cast`` command that
hangs says where with ``kill -QUIT PID``, and the orchestrator and the agent
send it to a component that did not stop in time before they kill it, so its
log shows what it was stuck in (cast.orchestrator.process).
"""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import os
import signal
import sys
import threading

__all__ = ["STACK_DUMP_SIGNAL", "dump_stacks_on_sigquit", "terminate_when_stdin_closes", "until_terminated"]

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


async def until_terminated() -> None:
    """Return once SIGINT or SIGTERM arrives (handled on the event loop, so no callback races the loop)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        # Not available off the main thread or on some platforms: then only cancellation ends the wait.
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    await stop.wait()


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
