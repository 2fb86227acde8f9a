"""The start barrier: every component of a starting system finishes start() before any run() begins.

The original CAST client configured every component, started them all, and only
then ran them, so a watch registered in ``start()`` sees what any component
writes in ``run()``. ``cast run`` holds the barrier of each server it starts,
waits until every component it launched reports STARTED, then releases it. A
server started any other way has no barrier: ``wait`` returns at once. A
component that joins or restarts later finds it released.
"""

from __future__ import annotations

import asyncio
import threading

__all__ = ["StartBarrier"]


class StartBarrier:
    """Released from the start unless :meth:`hold` is called before anyone waits."""

    def __init__(self) -> None:
        self._released = threading.Event()
        self._released.set()
        self._mutex = threading.Lock()
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = []

    @property
    def released(self) -> bool:
        """Whether run() may begin."""
        return self._released.is_set()

    def hold(self) -> None:
        """Hold run() back until :meth:`release` (the orchestrator, before it launches anything)."""
        self._released.clear()

    def release(self) -> None:
        """Let every waiter go, now and from now on; callable from any thread, more than once."""
        with self._mutex:
            self._released.set()
            waiters, self._waiters = self._waiters, []
        for loop, future in waiters:
            loop.call_soon_threadsafe(_resolve, future)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until released; False if ``timeout`` seconds passed first."""
        return self._released.wait(timeout)

    async def wait_async(self) -> None:
        """Wait on the running event loop until released."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[None] = loop.create_future()
        with self._mutex:
            if self._released.is_set():
                return
            self._waiters.append((loop, future))
        try:
            await future
        finally:
            with self._mutex:
                if (loop, future) in self._waiters:
                    self._waiters.remove((loop, future))  # the caller gave up (deadline, cancel)


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)
