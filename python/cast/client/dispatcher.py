"""One thread per component that runs its callbacks, one at a time: highest priority first, then in arrival order.

The thread also reads the sockets attached to it (:meth:`Dispatcher.attach`:
a shared-memory session that carries a watch's events, docs/client-protocol.md
"A watch's events on the session's socket"): an event read there is converted
and its callback run on this thread, with no hand-off between threads on the
way. While it has nothing to run, it waits in ``poll`` on those sockets and on
an eventfd of its own, which other threads write when they queue a call.
While one callback runs longer than :data:`STANDBY_S`, a standby thread reads
the sockets in its place (while the queue has room), so that a slow callback
lets events pile up in the component's queue as the gRPC stream's reader does,
rather than on the server.
"""

from __future__ import annotations

import array
import fcntl
import logging
import os
import select
import termios
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol

from cast.client.alarm import Alarm

__all__ = ["BACKLOG_BYTES", "HIGH", "LOW", "MEDIUM", "Dispatcher", "Source"]

HIGH, MEDIUM, LOW = 0, 1, 2
"""Priorities of queued calls: the dispatcher takes the highest pending one first (FIFO within one)."""

log = logging.getLogger("cast.component")

STANDBY_S = 0.01
"""How long one callback may run before the standby thread reads the attached sockets meanwhile."""

_BUSY_MS = 1  # how long the thread waits (for a call) while another thread reads a source

BACKLOG_BYTES = 64 << 10
"""With ``read_every_s``: after a read that found this much waiting in a source, the next comes at once (a burst)."""

_READABLE = select.POLLIN | select.POLLPRI | select.POLLERR | select.POLLHUP


class Source(Protocol):
    """A socket the dispatcher reads: a shared-memory session (:class:`cast.client.shm_session.ClientSession`)."""

    def fileno(self) -> int:
        """Its descriptor; -1 once it ended (the dispatcher then forgets it)."""
        ...

    def poll(self, wait: float = 0.0) -> bool:
        """Read what is there without waiting, handling each frame (on this thread); False if another thread is."""
        ...

    def reader(self) -> Callable[[], bool]:
        """``poll()`` as one callable, taken once: what the dispatcher thread calls when the socket is readable."""
        ...


class Dispatcher:
    """Runs queued calls on its own thread, in order; a failing callback is logged, not fatal.

    The queue is bounded by ``capacity`` so that a component whose callbacks
    are slow lags behind on the server (which keeps a bounded history and says
    so when the lag exceeds it) instead of growing without bound in memory.
    A blocking :meth:`submit` waits for room; ``on_space`` is called (on the
    dispatcher thread) when room appears after the queue was full. The
    attached sockets are read only while the queue has room: past it, what
    the server sends waits in the socket and then on the server, which lets
    the watch lag by the same rule.

    With ``read_every_s``, the attached sockets are read at most once in that
    many seconds (queued calls still run at once): what comes meanwhile waits
    in the socket and is read together; after a read that found
    :data:`BACKLOG_BYTES` or more waiting (a burst), the next comes at once. A reader that
    handles events in batches anyway (``cast record``) then wakes once per
    batch, not once per frame, and takes that much less CPU from the system
    it watches (docs/performance.md, "REC1: what recording costs").
    """

    def __init__(self, name: str, capacity: int = 10_000, read_every_s: float = 0.0) -> None:
        # deque append and popleft are atomic, so the queues need no lock of their own.
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
        self._stopping = False
        # Written by other threads when they queue a call while the thread waits (or may be about to).
        self._wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._sleeping = False
        self._closed = False  # the eventfd closed (after the thread ended)
        self._sources: dict[int, Source] = {}  # fd -> source; changed on this thread only
        self._readers: dict[int, Callable[[], bool]] = {}  # fd -> its source's reader(); as _sources
        self._attach: deque[Source] = deque()  # sources to add, from any thread
        self._read_every = read_every_s
        self._last_read = 0.0  # time.monotonic() of the last look at the sources
        self._poller = select.poll()
        self._poller.register(self._wake_fd, select.POLLIN)
        self._wake_poller = select.poll()  # the eventfd alone
        self._wake_poller.register(self._wake_fd, select.POLLIN)
        self._call_started = 0.0  # time.monotonic() at the start of the call running now; 0.0 between calls
        self._standby: threading.Thread | None = None  # started with the first source
        # The standby thread sleeps on this between callbacks, so an idle component's threads stay asleep; the
        # dispatcher sets it when a callback begins and it is not set already (cast.client.alarm says why).
        self._alarm: Alarm | None = None  # made with the standby thread
        self._alarm_set = False
        # Its set(STANDBY_S) and cancel() as calls made once: C calls, no Python frame, in the compiled build (alarm).
        self._arm_standby: Callable[[], None] | None = None
        self._disarm_standby: Callable[[], None] = _nothing
        self._thread.start()
        # Compared with threading.get_ident(), which is C, where threading.current_thread() would be a Python call
        # at every event (docs/performance-m8.md, "Claims and leases in C").
        self.ident = self._thread.ident
        """The dispatcher thread's ``threading.get_ident()``."""

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
        mine = threading.get_ident() == self.ident
        with self._lock:
            if block and self._pending >= self.capacity and not mine:
                self._was_full = True
                self._wait_for(lambda: self._pending < self.capacity)
            self._pending += 1
        self._calls[priority].append((fn, args))
        if not mine and self._sleeping:
            self._wake()

    def attach(self, source: Source) -> None:
        """Read ``source`` on the dispatcher thread from now on, until its ``fileno()`` is -1."""
        self._attach.append(source)
        if self._standby is None:
            with self._lock:
                if self._standby is None:
                    self._alarm = alarm = Alarm()
                    self._disarm_standby = alarm.canceller()
                    self._arm_standby = alarm.setter(STANDBY_S)
                    self._standby = threading.Thread(
                        target=self._stand_by, name=f"{self._thread.name}-standby", daemon=True
                    )
                    self._standby.start()
        self._wake()

    def _stand_by(self) -> None:
        """Read the sources while a callback runs long (they are the dispatcher's the rest of the time).

        Asleep on the alarm the dispatcher sets when a callback begins (and
        it is not set already) and cancels when the callback returns: it
        wakes only for a callback that runs STANDBY_S, never at a start. A frame read here is
        the source's to queue for the dispatcher (it knows it is not on the
        dispatcher thread); nothing here waits for room.
        """
        alarm = self._alarm
        assert alarm is not None  # made before this thread
        while True:
            self._watch_long_call(alarm)
            if self._stopping:
                return
            alarm.wait()
            # Cleared before _call_started is read again: a callback beginning meanwhile either sees it cleared and
            # sets the alarm, or began before that read, which then sees it.
            self._alarm_set = False

    def _watch_long_call(self, alarm: Alarm) -> None:
        """Read the sources for as long as the callback running now runs long; set the alarm for a young one."""
        while not self._stopping:
            started = self._call_started
            if not started:
                return  # between callbacks: asleep until the next one sets the alarm
            left = started + STANDBY_S - time.monotonic()
            if left > 0:
                self._alarm_set = True
                alarm.set(left)
                return
            if self.room() <= 0:
                time.sleep(STANDBY_S)
                continue
            sources = {source.fileno(): source for source in list(self._sources.values())}
            sources.pop(-1, None)
            if not sources:
                time.sleep(STANDBY_S)
                continue
            poller = select.poll()
            for fd in sources:
                poller.register(fd, _READABLE)
            for fd, _ in poller.poll(STANDBY_S * 1000):
                sources[fd].poll()

    def _wake(self) -> None:
        # Under the lock stop() closes the descriptor with: a submitter preempted between the check and the
        # write would otherwise write to a closed descriptor, or to whatever file reused its number.
        with self._lock:
            if not self._closed:
                os.eventfd_write(self._wake_fd, 1)

    def _wait_for(self, predicate: Callable[[], bool], timeout: float | None = None) -> bool:
        # Called with _lock held.
        self._waiters += 1
        try:
            return self._idle.wait_for(predicate, timeout)
        finally:
            self._waiters -= 1

    def _run(self) -> None:
        calls = self._calls
        read_now = False  # every source ready was read just now: no second poll before the call
        while True:
            if calls[HIGH] or calls[MEDIUM] or calls[LOW]:
                if (self._sources or self._attach) and not read_now:
                    self._read_sources(0)  # what came first, so that a higher priority's event goes first
                read_now = False
                fn, args = (calls[HIGH] or calls[MEDIUM] or calls[LOW]).popleft()
                self._call(fn, args)
                fn = args = None  # type: ignore[assignment]  # not kept: it may hold a lent value
                continue
            if self._stopping:
                return
            self._read_sources(None)
            read_now = True

    def _drain_wake(self) -> None:
        try:
            os.eventfd_read(self._wake_fd)
        except BlockingIOError:
            pass

    def _read_sources(self, timeout: float | None) -> None:
        """Read the sources that have something; ``timeout`` None: wait for them or a wake-up."""
        sources = self._sources
        for fd, source in list(sources.items()):
            if source.fileno() != fd:  # ended (its socket closed): forgotten before a new one may take its number
                del sources[fd], self._readers[fd]
                self._poller.unregister(fd)
        while self._attach:
            source = self._attach.popleft()
            fd = source.fileno()
            if fd >= 0 and sources.get(fd) is not source:
                sources[fd] = source
                self._readers[fd] = source.reader()
                self._poller.register(fd, _READABLE)
        if self._read_every and time.monotonic() < self._last_read + self._read_every:
            if timeout is None:
                self._wait_to_read()
            return  # too soon: what the sources have waits for the next read
        if timeout is None:
            self._sleeping = True
            if self._work_waiting():
                timeout = 0
        elif self._pending >= self.capacity:
            return  # full: what the sources have waits for room (and the server for the socket)
        try:
            ready = self._poller.poll(None if timeout is None else timeout * 1000)
        finally:
            self._sleeping = False
        if self._read_every and any(fd != self._wake_fd for fd, _ in ready):  # a source is read: its turn begins
            # After a burst (a history replayed) the next read comes at once, or the socket's buffer, read once
            # per read_every_s, would bound the rate.
            self._last_read = 0.0 if self._backlog() else time.monotonic()
        for fd, _ in ready:
            if fd == self._wake_fd:
                self._drain_wake()
                continue
            read = self._readers.get(fd)
            if read is not None and not read():
                # Another thread is reading it (and queues what it reads here): the socket stays readable until
                # it has, so wait for a call or a moment rather than spin on it.
                self._sleeping = True
                try:
                    if not (self._calls[HIGH] or self._calls[MEDIUM] or self._calls[LOW] or self._stopping):
                        self._wake_poller.poll(_BUSY_MS)
                finally:
                    self._sleeping = False

    def _backlog(self) -> bool:
        """Whether a source holds BACKLOG_BYTES or more unread (FIONREAD)."""
        waiting = array.array("i", [0])
        for fd in self._sources:
            try:
                fcntl.ioctl(fd, termios.FIONREAD, waiting, True)
            except OSError:  # ended meanwhile: forgotten at the next read
                continue
            if waiting[0] >= BACKLOG_BYTES:
                return True
        return False

    def _work_waiting(self) -> bool:
        """Whether a call, a source to attach or the stop waits (checked with ``_sleeping`` set: no wake-up lost)."""
        calls = self._calls
        return bool(calls[HIGH] or calls[MEDIUM] or calls[LOW] or self._attach or self._stopping)

    def _wait_to_read(self) -> None:
        """Wait for a call alone until ``read_every_s`` after the last read (or until stopped)."""
        self._sleeping = True
        try:
            left = self._last_read + self._read_every - time.monotonic()
            if left > 0 and not self._work_waiting():
                if self._wake_poller.poll(left * 1000):
                    self._drain_wake()
        finally:
            self._sleeping = False

    def _call(self, fn: Callable[..., object], args: tuple[object, ...]) -> None:
        self._call_started = time.monotonic()
        arm = self._arm_standby
        if arm is not None and not self._alarm_set:
            self._alarm_set = True
            arm()
        try:
            fn(*args)
        except Exception:
            log.exception("callback %s failed", getattr(fn, "__qualname__", fn))
        finally:
            # Not kept until the next call: a change may hold a value lent by shared memory (cast.client.shm).
            fn = args = None  # type: ignore[assignment]
            self._call_started = 0.0
            if self._alarm_set:
                # Over before the standby looked: it sleeps on (cheaper than waking it to find nothing running).
                self._alarm_set = False
                self._disarm_standby()
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
        self._stopping = True
        alarm = self._alarm
        if alarm is not None:
            alarm.set(0)  # the standby thread, asleep between callbacks
        self._wake()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
            standby = self._standby
            if standby is not None:
                standby.join(timeout)  # woken above; sees _stopping within STANDBY_S when it watches a call
            with self._lock:  # stop may come twice (a component closed twice)
                if self._thread.is_alive() or self._closed:
                    return
                self._closed = True
                os.close(self._wake_fd)
            if alarm is not None and standby is not None and not standby.is_alive():
                alarm.close()


def _nothing() -> None:
    """The standby's disarming before there is a standby (never called: nothing arms it then)."""
