"""Reaching working memories in the same process: direct calls on the core, no gRPC.

Used for components that run inside the server's process (``in_process: true``).
Every call goes through the component's :class:`cast.core.access.Access`, the
rulebook the gRPC servicers use too, so the rules are the remote ones: the same
checks, waits and errors, the same events (an entry only when asked for and
not under another's ODR lock), values still copied (the component serialises
on write and parses on read); only the network and the envelopes are gone.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import replace

from google.protobuf import descriptor_pb2

from cast.client.dispatcher import Dispatcher
from cast.client.loan import Loan
from cast.client.transport import EventSink
from cast.core.access import Access, event_for, run_sync
from cast.core.records import BatchOp, EntryRecord, Identity, LockMode, Operation, WriteResult
from cast.core.sessions import ComponentState, SessionStream
from cast.core.system import System
from cast.core.tasks import DecisionFeed, TaskOutcome, TaskRecord
from cast.core.watch import EventFilter, Subscription
from cast.errors import CastError
from cast.version import library_version

__all__ = ["LocalTransport"]


def _bytes(data: bytes | Loan, sa: str) -> bytes:
    """A write's value as bytes: a loan's, which spends it."""
    if isinstance(data, Loan):
        taken = data.take(sa, None)
        assert isinstance(taken, bytes)  # a loan taken in process is private memory
        return taken
    return data


def _done(write: Callable[[], WriteResult]) -> Future[WriteResult]:
    """A finished future holding ``write()``'s result or error."""
    future: Future[WriteResult] = Future()
    try:
        future.set_result(write())
    except CastError as exc:
        future.set_exception(exc)
    return future


class LocalTransport:
    """A component's direct connection to a :class:`System` in the same process."""

    delivers_on_writer_thread = True

    def __init__(self, system: System, identity: Identity) -> None:
        self.identity = identity
        self._system = system
        self._host = system.host
        self._sub_lock = threading.Lock()
        self._sub: Subscription | None = None
        self._sink: EventSink | None = None
        self._room: Callable[[], int] | None = None
        self._on_error: Callable[[CastError], None] = lambda err: None
        self._decision_sink: Callable[[TaskRecord], None] | None = None
        self._decisions: DecisionFeed | None = None
        self._session_id = ""
        self._session: SessionStream | None = None
        self._closing = threading.Event()
        self._access = Access(system, identity)
        self._state: Callable[[], ComponentState] | None = None

    def system_name(self) -> str:
        """The system's name."""
        return self._system.name

    def subarchitectures(self) -> list[str]:
        """The system's SA names."""
        return self._host.subarchitectures

    def loan(self, sa: str, type_name: str, header: bytes, size: int) -> Loan:
        """A loan in private memory: in process a value's bytes are handed over, not sent."""
        return Loan(sa, type_name, header, size)

    def add(self, sa: str, entry_id: str, type_name: str, data: bytes | Loan) -> WriteResult:
        """Create an entry."""
        data = _bytes(data, sa)
        return run_sync(self._system, self._access.write(BatchOp(Operation.ADD, sa, entry_id, type_name, data)))

    def overwrite(
        self, sa: str, entry_id: str, type_name: str, data: bytes | Loan, expected_version: int | None
    ) -> WriteResult:
        """Replace an entry's value."""
        op = BatchOp(Operation.OVERWRITE, sa, entry_id, type_name, _bytes(data, sa), expected_version)
        return run_sync(self._system, self._access.write(op))

    def add_async(self, sa: str, entry_id: str, type_name: str, data: bytes | Loan) -> Future[WriteResult]:
        """Create an entry; in process the write is done when this returns, so its future is too."""
        return _done(lambda: self.add(sa, entry_id, type_name, data))

    def overwrite_async(
        self, sa: str, entry_id: str, type_name: str, data: bytes | Loan, expected_version: int | None
    ) -> Future[WriteResult]:
        """Replace an entry's value; the future is done when this returns (in process)."""
        return _done(lambda: self.overwrite(sa, entry_id, type_name, data, expected_version))

    def delete(self, sa: str, entry_id: str, expected_version: int | None) -> WriteResult:
        """Delete an entry."""
        op = BatchOp(Operation.DELETE, sa, entry_id, expected_version=expected_version)
        return run_sync(self._system, self._access.write(op))

    def batch(self, ops: Sequence[BatchOp]) -> list[WriteResult]:
        """Apply writes in order, all or nothing."""
        return run_sync(self._system, self._access.batch(ops))

    def get(self, sa: str, entry_id: str) -> EntryRecord:
        """Read one entry (records are immutable, so sharing one is safe)."""
        return self._access.get(sa, entry_id)

    def get_by_type(self, sa: str, type_name: str, limit: int) -> list[EntryRecord]:
        """Read the entries of one type, newest first."""
        return self._access.get_by_type(sa, type_name, limit)[0]

    def exists(self, sa: str, entry_id: str) -> bool:
        """Whether an entry exists."""
        return self._access.exists(sa, entry_id)

    def lock(self, sa: str, entry_id: str, mode: LockMode, timeout: float | None, no_wait: bool) -> int:
        """Take a lock, waiting on this thread for its release up to ``timeout`` seconds."""
        return run_sync(self._system, self._access.lock(sa, entry_id, mode, no_wait), timeout)

    def unlock(self, sa: str, entry_id: str) -> int:
        """Release one level of a lock."""
        return run_sync(self._system, self._access.unlock(sa, entry_id))

    def register_schemas(self, files: Sequence[descriptor_pb2.FileDescriptorProto], sa: str | None = None) -> None:
        """Register entry types with the in-process server (the one server of every SA)."""
        run_sync(self._system, self._access.register_schemas(files))

    def set_event_sink(
        self, sink: EventSink, on_error: Callable[[CastError], None], room: Callable[[], int] | None = None,
        dispatcher: Dispatcher | None = None,
    ) -> None:
        """Where events go; they are delivered from the writer's thread, in order, never blocking it."""
        self._sink = sink
        self._on_error = on_error
        self._room = room

    def pump(self) -> None:
        """Deliver what was left pending while the sink was full."""
        self._wake()

    def _wake(self) -> None:
        # Called on the writer's thread; the lock keeps deliveries in order when
        # several threads write at once. Only as many events as the sink has
        # room for are taken, so a slow component lags (and past the history is
        # told so) instead of blocking the writer.
        with self._sub_lock:
            while self._sub is not None and self._sink is not None:
                budget = self._room() if self._room is not None else 0
                if self._room is not None and budget == 0:
                    return  # the sink remembers it was full and calls pump() when it drains
                try:
                    matches = self._access.take(self._sub, max_events=budget)
                except CastError as exc:
                    self._sub.close()
                    self._sub = None
                    self._on_error(exc)
                    return
                for m in matches:
                    self._sink(event_for(self._access, m), m.watch_ids)
                if not self._sub.behind:
                    return

    def watch(
        self,
        watch_id: int,
        filters: Sequence[EventFilter],
        start_revisions: dict[str, int] | None = None,
        latest: bool = False,
    ) -> dict[str, int]:
        """Create a watch (``latest``: conflating delivery, see :meth:`cast.core.access.Access.watch`)."""
        if self._sink is None:
            raise RuntimeError("set_event_sink must be called before watch")
        with self._sub_lock:
            if self._sub is None:
                self._sub = Subscription(self._host, self._wake)
            revisions = self._access.watch(self._sub, watch_id, filters, start_revisions, latest=latest)
        if start_revisions:
            self._wake()
        return revisions

    def cancel_watch(self, watch_id: int) -> None:
        """Remove a watch."""
        with self._sub_lock:
            if self._sub is not None:
                self._sub.cancel(watch_id)

    def propose(self, name: str, data_type: str, data: bytes, priority: int) -> TaskRecord:
        """Propose a task to the own SA's task manager."""
        return self._copy(run_sync(self._system, self._access.propose(name, data_type, data, priority)))

    @staticmethod
    def _copy(task: TaskRecord) -> TaskRecord:
        return replace(task)

    def retract(self, task_id: str) -> None:
        """Withdraw a task."""
        run_sync(self._system, self._access.retract(task_id))

    def complete(self, task_id: str, outcome: TaskOutcome, reason: str) -> None:
        """Report an adopted task's outcome."""
        run_sync(self._system, self._access.complete(task_id, outcome, reason))

    def report(self, name: str, value: float) -> None:
        """Record an outcome through the rulebook, as the servicer does."""
        self._access.report(name, value)

    def set_decision_sink(self, sink: Callable[[TaskRecord], None]) -> None:
        """Where task decisions go: handed over on the thread that decided (cast.core.tasks.DecisionFeed)."""
        self._decision_sink = sink
        self._decisions = self._access.decisions(self._decided)
        self._decided()

    def _decided(self) -> None:
        if self._decision_sink is None or self._decisions is None:
            return
        for task in self._decisions.take():
            self._decision_sink(task)

    def start_session(self, language: str, kind: str, state: Callable[[], ComponentState]) -> None:
        """Register and keep the session alive from a timer thread (cast.core.sessions.SessionStream)."""
        self._state = state
        self._session_id = self._access.register(language, kind, os.getpid(), socket.gethostname(), library_version())
        stream = self._session = self._access.session_stream()
        interval = max(0.05, self._system.sessions.lease_ms / 3000)
        stream.beat(self._session_id, state())

        def beat() -> None:
            while not self._closing.wait(interval):
                try:
                    stream.beat(self._session_id, state())
                except CastError:
                    return
            stream.end()

        threading.Thread(target=beat, name="cast-heartbeat", daemon=True).start()

    def report_state(self) -> None:
        """Record the component's state in its session now."""
        if self._session is not None and self._state is not None:
            try:
                self._session.beat(self._session_id, self._state())
            except CastError:
                pass  # the session ended: nothing to report to

    def await_run(self, stopping: threading.Event) -> bool:
        """Wait on the system's start barrier itself (in process: no AwaitRun call to make)."""
        while not stopping.is_set() and not self._closing.is_set():
            if self._system.barrier.wait(0.1):
                return True
        return False

    def close(self) -> None:
        """End the session; stop watching."""
        self._closing.set()
        if self._session is not None:
            self._session.end()
        if self._decisions is not None:
            self._decisions.close()
        with self._sub_lock:
            if self._sub is not None:
                self._sub.close()
                self._sub = None
