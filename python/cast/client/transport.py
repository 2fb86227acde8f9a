"""The boundary between the component API and the way it reaches a working memory.

Two implementations: :class:`~cast.client.grpc_transport.GrpcTransport` (a
remote server, over gRPC) and :class:`~cast.client.local_transport.LocalTransport`
(a component inside the server's process, no gRPC on the path). Both speak in
the core's record types, so the component code above them is one.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Protocol

from google.protobuf import descriptor_pb2

from cast.client.dispatcher import Dispatcher
from cast.client.loan import Loan
from cast.core.records import BatchOp, ChangeEvent, EntryRecord, Identity, LockMode, WriteResult
from cast.core.sessions import ComponentState
from cast.core.tasks import TaskOutcome, TaskRecord
from cast.core.watch import EventFilter
from cast.errors import CastError

__all__ = ["EventSink", "SystemInfo", "Transport"]

EventSink = Callable[[ChangeEvent, Sequence[int]], None]
"""Receives each event once with the ids of the watches it matched, in order."""


class SystemInfo(Protocol):
    """What a transport reports about the system (subset of cast.v1.SystemDescription)."""

    name: str


class Transport(Protocol):
    """Everything a component does to working memories and its task manager."""

    identity: Identity
    delivers_on_writer_thread: bool
    """True if the event sink is called on writers' threads (so it must never block)."""

    def loan(self, sa: str, type_name: str, header: bytes, size: int) -> Loan:
        """A place for ``size`` bytes of a value after its ``header`` (cast.client.loan), written with add/overwrite."""

    def add(self, sa: str, entry_id: str, type_name: str, data: bytes | Loan) -> WriteResult:
        """Create an entry."""

    def overwrite(
        self, sa: str, entry_id: str, type_name: str, data: bytes | Loan, expected_version: int | None
    ) -> WriteResult:
        """Replace an entry's value."""

    def add_async(self, sa: str, entry_id: str, type_name: str, data: bytes | Loan) -> Future[WriteResult]:
        """Create an entry without waiting for the answer: its future (errors arrive on it)."""

    def overwrite_async(
        self, sa: str, entry_id: str, type_name: str, data: bytes | Loan, expected_version: int | None
    ) -> Future[WriteResult]:
        """Replace an entry's value without waiting for the answer: its future."""

    def delete(self, sa: str, entry_id: str, expected_version: int | None) -> WriteResult:
        """Delete an entry."""

    def batch(self, ops: Sequence[BatchOp]) -> list[WriteResult]:
        """Apply writes in order, all or nothing (all in one SA's server)."""

    def get(self, sa: str, entry_id: str) -> EntryRecord:
        """Read one entry."""

    def get_by_type(self, sa: str, type_name: str, limit: int) -> list[EntryRecord]:
        """Read the entries of one type, newest first."""

    def exists(self, sa: str, entry_id: str) -> bool:
        """Whether an entry exists."""

    def lock(self, sa: str, entry_id: str, mode: LockMode, timeout: float | None, no_wait: bool) -> int:
        """Take a lock (waiting up to ``timeout`` seconds, None: forever); return its depth."""

    def unlock(self, sa: str, entry_id: str) -> int:
        """Release one level of a lock; return the remaining depth."""

    def register_schemas(self, files: Sequence[descriptor_pb2.FileDescriptorProto], sa: str | None = None) -> None:
        """Register entry type descriptors with the server of ``sa`` (None: with every server)."""

    def watch(
        self,
        watch_id: int,
        filters: Sequence[EventFilter],
        start_revisions: dict[str, int] | None = None,
        latest: bool = False,
    ) -> dict[str, int]:
        """Create a watch; return each SA's revision when it took effect.

        ``latest``: delivery "latest" (the server sends only the newest of the
        changes of an entry pending for this watch, with how many it skipped).
        """

    def cancel_watch(self, watch_id: int) -> None:
        """Remove a watch."""

    def set_event_sink(
        self, sink: EventSink, on_error: Callable[[CastError], None], room: Callable[[], int] | None = None,
        dispatcher: Dispatcher | None = None,
    ) -> None:
        """Where events (and a fatal watch error, e.g. history expired) go.

        ``room()`` says how many events the sink can take without blocking;
        a transport that delivers on a writer's thread uses it so that it never
        blocks the writer, and leaves the rest pending until :meth:`pump`.
        ``dispatcher``: the component's, which a transport may have read the
        events itself (the sink is then called on it).
        """

    def pump(self) -> None:
        """Deliver events left pending for lack of room (called when the sink has room again)."""

    def propose(self, name: str, data_type: str, data: bytes, priority: int) -> TaskRecord:
        """Propose a task to the own SA's task manager."""

    def retract(self, task_id: str) -> None:
        """Withdraw a task."""

    def complete(self, task_id: str, outcome: TaskOutcome, reason: str) -> None:
        """Report an adopted task's outcome."""

    def set_decision_sink(self, sink: Callable[[TaskRecord], None]) -> None:
        """Where task decisions about this component go."""

    def report(self, name: str, value: float) -> None:
        """Record an outcome the component measured, with its own SA's server (Inspection.Report)."""

    def start_session(self, language: str, kind: str, state: Callable[[], ComponentState]) -> None:
        """Register and keep a session alive (heartbeats report ``state()``)."""

    def report_state(self) -> None:
        """Tell the server the component's state now, not at the next heartbeat."""

    def await_run(self, stopping: threading.Event) -> bool:
        """Block until the system's start barrier is released (True), or ``stopping`` is set (False)."""

    def system_name(self) -> str:
        """The system's name."""

    def subarchitectures(self) -> list[str]:
        """The system's SA names."""

    def close(self) -> None:
        """End the session and release every resource."""
