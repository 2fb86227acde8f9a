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
import signal
import sys

__all__ = ["STACK_DUMP_SIGNAL", "dump_stacks_on_sigquit", "until_terminated"]

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
