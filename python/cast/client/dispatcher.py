"""One thread per component that runs its callbacks, one at a time, in arrival order."""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

__all__ = ["Dispatcher"]

log = logging.getLogger("cast.component")


class Dispatcher:
    """Runs queued calls on its own thread, in order; a failing callback is logged, not fatal."""

    def __init__(self, name: str) -> None:
        self._queue: queue.SimpleQueue[tuple[Callable[..., object], tuple[object, ...]] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=f"cast-dispatch-{name}", daemon=True)
        self._idle = threading.Condition()
        self._pending = 0
        self._thread.start()

    @property
    def thread(self) -> threading.Thread:
        """The dispatcher thread (callbacks run on it)."""
        return self._thread

    def submit(self, fn: Callable[..., object], *args: object) -> None:
        """Queue ``fn(*args)``."""
        with self._idle:
            self._pending += 1
        self._queue.put((fn, args))

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            fn, args = item
            try:
                fn(*args)
            except Exception:  # noqa: BLE001 - one bad callback must not stop the others
                log.exception("callback %s failed", getattr(fn, "__qualname__", fn))
            finally:
                with self._idle:
                    self._pending -= 1
                    if self._pending == 0:
                        self._idle.notify_all()

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every queued call has run; False on timeout."""
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0, timeout)

    def stop(self, timeout: float | None = 5.0) -> None:
        """Run what is queued, then end the thread."""
        self._queue.put(None)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
