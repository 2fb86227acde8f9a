"""The component's dispatcher: order, its bound, blocking submitters, drain and the on_space signal."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from cast.client.dispatcher import BACKLOG_BYTES, STANDBY_S, Dispatcher
from tests.conftest import wait_for


def test_calls_run_in_order_on_the_dispatcher_thread_and_drain_waits_for_them() -> None:
    d = Dispatcher("t")
    ran: list[tuple[int, threading.Thread]] = []
    gate = threading.Event()
    d.submit(gate.wait, 10)
    for i in range(100):
        d.submit(lambda i=i: ran.append((i, threading.current_thread())))
    assert not d.drain(0.05)  # the first call still waits at the gate
    gate.set()
    assert d.drain(10)
    assert [i for i, _ in ran] == list(range(100))
    assert {t for _, t in ran} == {d.thread}
    d.stop()


def test_a_full_queue_blocks_submitters_until_room_and_signals_space_at_half() -> None:
    d = Dispatcher("t", capacity=4)
    spaces: list[int] = []
    d.on_space = lambda: spaces.append(1)
    gate = threading.Event()
    for _ in range(4):
        d.submit(gate.wait, 10)
    assert d.room() == 0  # full: and flagged, so on_space follows once it drains
    submitted = threading.Event()

    def blocked_submitter() -> None:
        d.submit(lambda: None)  # blocks: the queue is full
        submitted.set()

    threading.Thread(target=blocked_submitter, daemon=True).start()
    assert not submitted.wait(0.1)
    d.submit(lambda: None, block=False)  # a non-blocking submit goes over the bound instead
    gate.set()
    assert submitted.wait(10)  # woken when room appeared
    assert d.drain(10)
    # Once, when the queue was back to half: on the dispatcher thread, before the later calls ran.
    assert spaces == [1]
    assert d.room() == 4
    d.stop()


class _Socket:
    """A source as a shared-memory session is one: a socket pair's end, read by whichever thread polls it."""

    def __init__(self) -> None:
        self.mine, self.peer = socket.socketpair()
        self.mine.setblocking(False)
        self.readers: list[str] = []
        self.lock = threading.Lock()

    def fileno(self) -> int:
        return self.mine.fileno()

    def poll(self, wait: float = 0.0) -> bool:
        if not self.lock.acquire(blocking=False):
            return False
        try:
            while True:
                try:
                    data = self.mine.recv(4096)
                except BlockingIOError:
                    return True
                self.readers.extend([threading.current_thread().name] * len(data))
        finally:
            self.lock.release()

    def reader(self) -> Callable[[], bool]:
        return self.poll

    def close(self) -> None:
        self.mine.close()
        self.peer.close()


def test_an_attached_socket_is_read_on_the_dispatcher_thread_and_while_a_callback_runs_long_by_the_standby() -> None:
    d = Dispatcher("t")
    source = _Socket()
    d.attach(source)
    source.peer.send(b"a")
    wait_for(lambda: source.readers == ["cast-dispatch-t"], what="the byte read by the dispatcher")
    gate = threading.Event()
    d.submit(gate.wait, 10)  # a callback that runs long: the standby reads meanwhile
    time.sleep(3 * STANDBY_S)
    source.peer.send(b"b")
    wait_for(lambda: source.readers[1:] == ["cast-dispatch-t-standby"], what="the byte read by the standby")
    gate.set()
    assert d.drain(10)
    time.sleep(3 * STANDBY_S)  # the standby's last wait on the socket is over
    source.peer.send(b"c")
    wait_for(lambda: source.readers[2:] == ["cast-dispatch-t"], what="the dispatcher's again")
    d.stop()
    source.close()
    assert not d.thread.is_alive()


class _CountingPoller:
    """The dispatcher's poller, noting each wait (its timeout in ms, None: until something comes) in ``seen``."""

    def __init__(self, poller: Any, seen: list[object]) -> None:
        self._poller = poller
        self._seen = seen

    def poll(self, timeout: float | None = None) -> Any:
        self._seen.append(("poll", timeout))
        return self._poller.poll(timeout)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._poller, name)


class _Events(_Socket):
    """A source whose bytes are events: each one read queues its callback, as a session's EVENTS frames do."""

    def __init__(self, dispatcher: Dispatcher, seen: list[object]) -> None:
        super().__init__()
        self.dispatcher = dispatcher
        self.seen = seen

    def poll(self, wait: float = 0.0) -> bool:
        before = len(self.readers)
        done = super().poll(wait)
        for _ in range(len(self.readers) - before):
            self.dispatcher.submit(lambda: self.seen.append(("call",)), block=False)
        return done


def test_an_event_read_on_the_dispatcher_goes_to_its_callback_without_a_second_poll() -> None:
    """Every source that was ready has just been read: polling them again before the call costs a system call."""
    d = Dispatcher("t")
    seen: list[object] = []
    d._poller = _CountingPoller(d._poller, seen)  # type: ignore[assignment]
    source = _Events(d, seen)
    d.attach(source)
    wait_for(lambda: d._sources, what="the source attached")
    source.peer.send(b"a")
    wait_for(lambda: ("call",) in seen, what="the callback")
    assert seen[seen.index(("call",)) - 1] == ("poll", None), seen
    d.stop()
    source.close()


def test_a_full_queue_leaves_the_attached_socket_unread() -> None:
    d = Dispatcher("t", capacity=2)
    source = _Socket()
    d.attach(source)
    gate = threading.Event()
    d.submit(gate.wait, 10)
    d.submit(lambda: None)  # full: what the socket has waits there (and then on the server)
    time.sleep(3 * STANDBY_S)
    source.peer.send(b"x")
    time.sleep(5 * STANDBY_S)
    assert source.readers == []
    gate.set()
    wait_for(lambda: source.readers == ["cast-dispatch-t"], what="the byte read once there is room")
    d.stop()
    source.close()


def _wake_ups(thread: threading.Thread) -> int:
    """How many times ``thread`` went to sleep and woke (its voluntary context switches)."""
    status = open(f"/proc/self/task/{thread.native_id}/status").read()
    return int(status.split("voluntary_ctxt_switches:")[1].split()[0])


def _with_standby() -> tuple[Dispatcher, _Socket, threading.Thread]:
    """A dispatcher reading a socket, after one callback: its standby thread started and asleep."""
    d = Dispatcher("t")
    source = _Socket()
    d.attach(source)
    d.submit(lambda: None)
    assert d.drain(10)
    assert d._standby is not None
    return d, source, d._standby


def test_an_idle_dispatchers_threads_stay_asleep() -> None:
    """Between callbacks the standby thread waits for one to begin: it does not wake every STANDBY_S."""
    d, source, standby = _with_standby()
    time.sleep(5 * STANDBY_S)
    before = (_wake_ups(standby), _wake_ups(d.thread))
    time.sleep(50 * STANDBY_S)  # idle: a thread polling every STANDBY_S would wake ~50 times
    after = (_wake_ups(standby), _wake_ups(d.thread))
    assert after[0] - before[0] <= 3 and after[1] - before[1] <= 3, (before, after)
    # ... and it still watches a callback that runs long.
    gate = threading.Event()
    d.submit(gate.wait, 10)
    time.sleep(3 * STANDBY_S)
    source.peer.send(b"b")
    wait_for(lambda: source.readers == ["cast-dispatch-t-standby"], what="the byte read by the standby")
    gate.set()
    d.stop()
    source.close()
    assert not d.thread.is_alive() and not standby.is_alive()


def test_a_callbacks_start_does_not_wake_the_standby_thread() -> None:
    """The standby looks again STANDBY_S after a callback begins by an alarm, which a short callback cancels.

    Woken at every start, it took a core and the GIL at the moment each event's callback ran (a camera
    frame's read: docs/performance-m8.md, "The standby thread's alarm").
    """
    d, source, standby = _with_standby()
    woken: list[int] = []
    before = [0]

    def short() -> None:
        time.sleep(STANDBY_S / 2)
        woken.append(_wake_ups(standby) - before[0])

    time.sleep(5 * STANDBY_S)
    first = _wake_ups(standby)
    for _ in range(10):
        time.sleep(2 * STANDBY_S)
        before[0] = _wake_ups(standby)
        d.submit(short)
        assert d.drain(10)
    time.sleep(2 * STANDBY_S)
    assert woken.count(0) >= 8, woken  # not at a callback's start (a loaded machine may delay a thread)
    # ... nor after: a callback that returned within STANDBY_S cancelled its alarm.
    assert _wake_ups(standby) - first <= 2, _wake_ups(standby) - first
    d.stop()
    source.close()


def test_a_dispatcher_with_a_standby_may_be_stopped_twice() -> None:
    """A component closed twice stops its dispatcher twice: the second finds the alarm closed and does nothing."""
    d, source, _ = _with_standby()
    d.stop()
    d.stop()
    source.close()
    assert not d.thread.is_alive()


def test_a_submit_racing_stop_never_writes_to_a_closed_wake_descriptor(monkeypatch: Any) -> None:
    """A thread that submits as the component stops, preempted just before its wake-up write, as a decision
    arriving at close() was (EBADF in its thread; worse, the number may be another file's by then)."""
    d = Dispatcher("t")
    wait_for(lambda: d._sleeping, what="the dispatcher asleep")
    write = os.eventfd_write
    in_write, go = threading.Event(), threading.Event()

    def preempted_write(fd: int, value: int) -> None:
        if threading.current_thread().name == "submitter":
            in_write.set()
            go.wait(10)  # stop() runs meanwhile: it must not close the descriptor under this write
        write(fd, value)

    monkeypatch.setattr(os, "eventfd_write", preempted_write)
    errors: list[BaseException] = []

    def submit() -> None:
        try:
            d.submit(lambda: None)
        except OSError as exc:
            errors.append(exc)

    submitter = threading.Thread(target=submit, name="submitter")
    submitter.start()
    assert in_write.wait(10)
    stopper = threading.Thread(target=d.stop)
    stopper.start()
    time.sleep(0.2)  # long enough for stop() to end the thread and close the descriptor, were it allowed to
    go.set()
    submitter.join(10)
    stopper.join(10)
    assert not errors, errors
    assert not d.thread.is_alive()


class _Timed(_Socket):
    """A source that notes, in ``seen``, each read of bytes (with its CLOCK_MONOTONIC time)."""

    def __init__(self, seen: list[tuple[str, float]]) -> None:
        super().__init__()
        self.seen = seen

    def poll(self, wait: float = 0.0) -> bool:
        before = len(self.readers)
        done = super().poll(wait)
        if len(self.readers) > before:
            self.seen.append(("read", time.monotonic()))
        return done


def _read_once_read_every(every: float) -> tuple[Dispatcher, _Timed, list[tuple[str, float]]]:
    """A dispatcher with ``read_every_s=every`` and a timed source, whose first byte it has read."""
    d = Dispatcher("t", read_every_s=every)
    seen: list[tuple[str, float]] = []
    source = _Timed(seen)
    d.attach(source)
    source.peer.send(b"a")  # a few bytes: the next read waits its turn
    wait_for(lambda: len(seen) == 1, what="the first byte read")
    return d, source, seen


def test_with_read_every_s_the_sockets_are_read_at_most_that_often_and_calls_still_run_at_once() -> None:
    every = 1.0
    d, source, seen = _read_once_read_every(every)
    source.peer.send(b"b")  # too soon after the first read: it waits in the socket
    d.submit(lambda: seen.append(("call", time.monotonic())))
    wait_for(lambda: len(seen) == 3, what="the call, and the second byte read")
    assert [kind for kind, _ in seen] == ["read", "call", "read"], seen  # the call did not wait for the read
    # At least `every` after the first look at the socket, which came a moment before the first read's note.
    assert seen[2][1] - seen[0][1] >= 0.9 * every, seen
    assert source.readers == ["cast-dispatch-t"] * 2
    d.stop()
    source.close()
    assert not d.thread.is_alive()


def test_with_read_every_s_a_read_that_found_a_burst_is_followed_by_the_next_at_once() -> None:
    every = 3.0
    d, source, seen = _read_once_read_every(every)
    source.peer.sendall(b"x" * 2 * BACKLOG_BYTES)  # all of it waiting when that turn comes: a burst
    wait_for(lambda: len(source.readers) == 1 + 2 * BACKLOG_BYTES, what="the burst read")
    burst_read = seen[-1][1]
    source.peer.send(b"y")
    wait_for(lambda: len(source.readers) == 2 + 2 * BACKLOG_BYTES, what="the byte after the burst")
    assert burst_read - seen[0][1] >= 0.9 * every, seen  # the burst waited for its turn
    assert seen[-1][1] - burst_read < every, seen  # the read after it did not
    d.stop()
    source.close()
