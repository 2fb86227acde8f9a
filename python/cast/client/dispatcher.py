"""One thread per component that runs its callbacks, one at a time: highest priority first, then in arrival order."""

from __future__ import annotations

import logging
import queue
import threading
from collections import deque
from collections.abc import Callable

__all__ = ["HIGH", "LOW", "MEDIUM", "Dispatcher"]

HIGH, MEDIUM, LOW = 0, 1, 2
"""Priorities of queued calls: the dispatcher takes the highest pending one first (FIFO within one)."""

log = logging.getLogger("cast.component")


class Dispatcher:
    """Runs queued calls on its own thread, in order; a failing callback is logged, not fatal.

    The queue is bounded by ``capacity`` so that a component whose callbacks
    are slow lags behind on the server (which keeps a bounded history and says
    so when the lag exceeds it) instead of growing without bound in memory.
    A blocking :meth:`submit` waits for room; ``on_space`` is called (on the
    dispatcher thread) when room appears after the queue was full.
    """

    def __init__(self, name: str, capacity: int = 10_000) -> None:
        # One token per queued call wakes the thread; it then takes the oldest call of the highest priority
        # (deque append and popleft are atomic, so the queues need no lock of their own).
        self._queue: queue.SimpleQueue[bool | None] = queue.SimpleQueue()
        self._calls: tuple[deque[tuple[Callable[..., object], tuple[object, ...]]], ...] = (deque(), deque(), deque())
        self._thread = threading.Thread(target=self._run, name=f"cast-dispatch-{name}", daemon=True)
        # A plain lock, taken directly on the common paths: the writer submits and
        # the dispatcher thread finishes a callback at nearly the same moment for
        # every event, and each extra step under the lock widens that meeting.
        self._lock = threading.Lock()
        self._idle = threading.Condition(self._lock)
        self._waiters = 0  # threads in _idle.wait_for (blocked submitters, drain); under _lock
        self._pending = 0
        self.capacity = capacity
        self.on_space: Callable[[], None] | None = None
        self._was_full = False
        self._thread.start()

    def room(self) -> int:
        """How many more calls fit before the queue is full."""
        room = self.capacity - self._pending  # read without the lock: a budget, stale by at most a few calls
        if room > 0:
            return room
        with self._lock:  # full: flag it under the lock, so the dispatcher thread sees it when it frees room
            room = self.capacity - self._pending
            if room <= 0:
                self._was_full = True
            return max(0, room)

    @property
    def thread(self) -> threading.Thread:
        """The dispatcher thread (callbacks run on it)."""
        return self._thread

    def submit(self, fn: Callable[..., object], *args: object, block: bool = True, priority: int = MEDIUM) -> None:
        """Queue ``fn(*args)`` at ``priority`` (HIGH, MEDIUM, LOW); with ``block``, wait while the queue is full."""
        with self._lock:
            if block and self._pending >= self.capacity and threading.current_thread() is not self._thread:
                self._was_full = True
                self._wait_for(lambda: self._pending < self.capacity)
            self._pending += 1
        self._calls[priority].append((fn, args))
        self._queue.put(True)

    def _wait_for(self, predicate: Callable[[], bool], timeout: float | None = None) -> bool:
        # Called with _lock held.
        self._waiters += 1
        try:
            return self._idle.wait_for(predicate, timeout)
        finally:
            self._waiters -= 1

    def _run(self) -> None:
        while True:
            if self._queue.get() is None:
                return
            calls = self._calls
            fn, args = (calls[HIGH] or calls[MEDIUM] or calls[LOW]).popleft()
            try:
                fn(*args)
            except Exception:
                log.exception("callback %s failed", getattr(fn, "__qualname__", fn))
            finally:
                # Not kept until the next call: a change may hold a value lent by shared memory (cast.client.shm).
                fn = args = None  # type: ignore[assignment]
                with self._lock:
                    self._pending -= 1
                    if self._waiters:
                        self._idle.notify_all()
                    resume = self._was_full and self._pending <= self.capacity // 2
                    if resume:
                        self._was_full = False
                if resume and self.on_space is not None:
                    self.on_space()

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every queued call has run; False on timeout."""
        with self._lock:
            return self._wait_for(lambda: self._pending == 0, timeout)

    def stop(self, timeout: float | None = 5.0) -> None:
        """Run what is queued, then end the thread."""
        self._queue.put(None)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
