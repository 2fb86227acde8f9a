"""Waiting for SIGINT or SIGTERM in a long-running asyncio command (`cast serve`, `cast agent`)."""

from __future__ import annotations

import asyncio
import contextlib
import signal

__all__ = ["until_terminated"]


async def until_terminated() -> None:
    """Return once SIGINT or SIGTERM arrives (handled on the event loop, so no callback races the loop)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        # Not available off the main thread or on some platforms: then only cancellation ends the wait.
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    await stop.wait()
