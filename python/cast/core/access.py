"""One rulebook for every caller: what a component may do and see, over gRPC and in process alike.

:class:`Access` is one caller (an identity) in front of one :class:`System`.
Every rule a caller meets is here or below it: identity and permissions,
waiting for a lock (blocking with a deadline, or not at all), answering only
once what a call saw is durable, task validation, creating a watch (the
history check included) and what an event may carry for this caller (no
entry written under another's ODR lock, no entry it did not ask for). The
gRPC servicers and the in-process transport only translate to and from it.

Calls that may wait are written once, as *steps*: a generator that yields
what it waits for (:class:`Durable`, :class:`Unlocked`) and returns the
result. :func:`run_sync` drives them on the caller's thread (in process),
:func:`run_async` on an event loop (the servicers); neither holds a mutex
while it waits.

What the rulebook answers and hands out is also what it counts
(:mod:`cast.core.metrics`): reads, applied and refused writes, locks and
their waits, events delivered to watchers. So every transport counts alike.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass
from typing import TypeVar

from cast.core.arena import Placed
from cast.core.describe import COUNTERS, SystemSummary, describe
from cast.core.metrics import Metrics
from cast.core.records import BatchOp, ChangeEvent, EntryRecord, Identity, LockMode, WriteResult
from cast.core.sessions import SessionStream
from cast.core.shared import Lent, SharedSession
from cast.core.system import System
from cast.core.tasks import DecisionFeed, TaskOutcome, TaskRecord
from cast.core.watch import EventFilter, Match, Subscription
from cast.errors import (
    CastError,
    DeadlineExceededError,
    HistoryExpiredError,
    InvalidArgumentError,
    LockedError,
    NoSessionError,
)

__all__ = [
    "DURABLE", "Access", "Durable", "Listing", "Steps", "Unlocked", "event_for", "resume_async", "run_async",
    "run_sync", "settle_at_once",
]

T = TypeVar("T")


@dataclass(frozen=True)
class Durable:
    """Wait until every write made so far is durable (at once without a journal writers wait for)."""


@dataclass(frozen=True)
class Unlocked:
    """Wait until the lock on (sa, id) is released; ``blocked`` says why, for the deadline's error."""

    sa: str
    entry_id: str
    blocked: LockedError


@dataclass(frozen=True)
class Listing:
    """A WM's entries as a tool lists them, without their values."""

    entries: list[EntryRecord]
    revision: int
    pending_writes: int
    bytes: int
    max_bytes: int
    shared_bytes: int


Steps = Generator[Durable | Unlocked, None, T]
"""A call that may wait: yields what it waits for, returns its result."""

DURABLE = Durable()
"""The one :class:`Durable` step (every write yields it: no allocation per call)."""


class Access:
    """The calls of one caller, with every rule it is subject to."""

    def __init__(self, system: System, who: Identity) -> None:
        self.system = system
        self.who = who
        self._host = system.host
        self._metrics: Metrics | None = system.metrics.active

    # ------------------------------------------------------------------ reads
    # Reads see durable state only and never wait (cast.core.host).

    def get(self, sa: str, entry_id: str) -> EntryRecord:
        """One entry; NOT_FOUND, or FAILED_PRECONDITION if another holds it ODR-locked."""
        record = self._host.get(self.who, sa, entry_id)
        if self._metrics is not None:
            self._metrics.read(self.who, sa, 1, len(record.data))
        return record

    def get_by_type(self, sa: str, type_name: str, limit: int = 0) -> tuple[list[EntryRecord], int]:
        """Entries of one type, newest first (ODR-locked ones of others left out), and the revision read."""
        records, revision = self._host.get_by_type(self.who, sa, type_name, limit)
        if self._metrics is not None:
            self._metrics.read(self.who, sa, len(records), sum(len(r.data) for r in records))
        return records, revision

    def exists(self, sa: str, entry_id: str) -> bool:
        """Whether an entry exists."""
        found = self._host.exists(self.who, sa, entry_id)
        if self._metrics is not None:
            self._metrics.read(self.who, sa, 0, 0)
        return found

    # ----------------------------------------------------------------- writes
    # Answered, refusals included, only once what they saw is durable.

    def write(self, op: BatchOp) -> Steps[WriteResult]:
        """One add, overwrite or delete (a large value is kept in shared memory first: cast.core.shared)."""
        m = self._metrics
        shared = self.system.shared
        if shared is not None:
            op = shared.place(op)
        refused: CastError | None = None
        try:
            result = self._host.write(self.who, op)
        except CastError as exc:
            if m is not None:
                m.refused(self.who)
            refused = exc
        if refused is not None:  # yielded outside the handler (mypyc)
            yield DURABLE  # a refusal names versions and holders: only durable ones
            raise refused
        if m is not None:
            m.wrote(self.who, op)  # counted once applied, before the wait for the journal
        yield DURABLE
        return result

    def batch(self, ops: Sequence[BatchOp]) -> Steps[list[WriteResult]]:
        """Writes in order, all or nothing."""
        m = self._metrics
        shared = self.system.shared
        if shared is not None:
            ops = [shared.place(op) for op in ops]
        refused: CastError | None = None
        try:
            results = self._host.batch(self.who, ops)
        except CastError as exc:
            if m is not None:
                m.refused(self.who)
            refused = exc
        if refused is not None:  # yielded outside the handler (mypyc)
            yield DURABLE
            raise refused
        if m is not None:
            m.wrote_batch(self.who, ops)
        yield DURABLE
        return results

    def register_schemas(self, files: Sequence[object]) -> Steps[list[str]]:
        """Register entry types (see cast.core.schemas); the message types they define."""
        return self._settled(lambda: self.system.schemas.register(files))  # type: ignore[arg-type]

    # ------------------------------------------------------------------ locks

    def lock(self, sa: str, entry_id: str, mode: LockMode, no_wait: bool = False) -> Steps[int]:
        """Take a lock (re-entrant); wait for another holder unless ``no_wait``; the depth."""
        waited_from = 0  # monotonic ns of the first wait; a wait is counted once, however it ends
        try:
            while True:
                blocked: LockedError | None = None
                try:
                    depth = yield from self._settled(lambda: self._host.try_lock(self.who, sa, entry_id, mode))
                except LockedError as exc:
                    if no_wait or isinstance(exc, NoSessionError):
                        raise
                    if not waited_from:
                        waited_from = time.monotonic_ns()
                    blocked = exc
                if blocked is not None:  # yielded outside the handler (mypyc)
                    yield Unlocked(sa, entry_id, blocked)
                    continue
                if self._metrics is not None:
                    self._metrics.locked(self.who, sa)
                return depth
        finally:
            if waited_from and self._metrics is not None:
                self._metrics.lock_waited(self.who, sa, time.monotonic_ns() - waited_from)

    def unlock(self, sa: str, entry_id: str) -> Steps[int]:
        """Release one level of the caller's lock; the remaining depth."""
        return self._settled(lambda: self._host.unlock(self.who, sa, entry_id))

    # ------------------------------------------------------------------ tasks

    def propose(self, name: str, data_type: str = "", data: bytes = b"", priority: int = 0) -> Steps[TaskRecord]:
        """Propose a task to the caller's SA's task manager."""
        tasks = self.system.tasks
        return self._settled(lambda: tasks.propose(self.who, name, data_type, data, priority))

    def retract(self, task_id: str) -> Steps[TaskRecord]:
        """Withdraw a waiting or adopted task of the caller."""
        return self._settled(lambda: self.system.tasks.retract(self.who, task_id))

    def complete(self, task_id: str, outcome: TaskOutcome | int, reason: str = "") -> Steps[TaskRecord]:
        """Report the outcome of an adopted task of the caller."""
        return self._settled(lambda: self.system.tasks.complete(self.who, task_id, outcome, reason))

    def tasks(self, sa: str = "") -> Steps[list[TaskRecord]]:
        """The live tasks of one SA or all, once their states are durable."""
        return self._settled(lambda: self.system.tasks.tasks(sa))

    def decisions(self, wake: Callable[[], None]) -> DecisionFeed:
        """The task manager's decisions about the caller's own tasks, made before and after this call."""
        return DecisionFeed(self.system.tasks, self.who.component_id, wake)

    # --------------------------------------------------------------- sessions

    def register(self, language: str, kind: str, pid: int, host: str, library_version: str) -> str:
        """Start a session for the caller (its locks and tasks live as long as it does); its id."""
        return self.system.sessions.register(self.who, language, kind, pid, host, library_version)

    def session_stream(self) -> SessionStream:
        """The heartbeats that keep one of the caller's sessions alive, and end it when they end."""
        return SessionStream(self.system.sessions, self.who)

    # ------------------------------------------------------------- inspection
    # What tools read: counted as reads of the caller, like any other.

    def describe(self, endpoint: str, served: Mapping[str, str], elsewhere: Mapping[str, str]) -> SystemSummary:
        """This server's SAs (``served``: where each is; ``elsewhere``: the SAs of other servers) and components."""
        return describe(self.system, endpoint, served, elsewhere)

    def list_entries(self, sa: str, type_name: str = "", limit: int = 0) -> Listing:
        """The entries of one WM without their values, oldest write first (the newest ``limit`` if given)."""
        if not sa:
            raise InvalidArgumentError("name the subarchitecture to list")
        host = self._host
        revision = host.revision(sa)  # NOT_FOUND for an SA not hosted here
        records = host.all_entries(sa)
        if type_name:
            records = [r for r in records if r.type == type_name]
        if limit:
            records = records[-limit:]
        if self._metrics is not None:
            self._metrics.read(self.who, sa, len(records), 0)
        # A listing never carries values: an entry another holds ODR-locked is listed, its value is not read.
        bare = [EntryRecord(r.subarchitecture, r.id, r.type, b"", r.version, r.author, r.modified_ns, r.revision)
                for r in records]
        return Listing(bare, revision, host.pending_writes(sa), host.total_bytes(sa), host.limits.max_total_bytes,
                       host.shared_bytes(sa))

    def task_statistics(self, sa: str = "") -> list[tuple[str, str, dict[str, int]]]:
        """Per SA (one, or every SA here): its policy and its decisions counted since the server started."""
        tasks = self.system.tasks
        out = []
        for name in [sa] if sa else self._host.subarchitectures:
            policy = tasks.policy(name).describe()  # NOT_FOUND for an SA not hosted here
            out.append((name, policy, {k: tasks.counters[name][k] for k in COUNTERS}))
        return out

    # --------------------------------------------------------------- outcomes

    def report(self, name: str, value: float) -> None:
        """Record an outcome the caller measured, under its own id (refusals: :meth:`cast.core.reports.Reports.report`).

        Kept whether or not counting is on (it is the caller's own call), and
        never journaled, so nothing waits for durability.
        """
        self.system.metrics.report(self.who.component_id, name, value)

    # ---------------------------------------------------------------- watches

    def watch(
        self,
        sub: Subscription,
        watch_id: int,
        filters: Sequence[EventFilter],
        start_revisions: Mapping[str, int] | None = None,
        history_id: str = "",
        latest: bool = False,
    ) -> dict[str, int]:
        """Add a watch to ``sub``; every WM's revision. A resume into another history is refused.

        ``latest``: conflating delivery (:meth:`cast.core.watch.Subscription.add_watch`).
        """
        if history_id and start_revisions and history_id != self.system.history_id:
            raise HistoryExpiredError(
                f"this server's history ({self.system.history_id}) is not the one the watch resumes from "
                f"({history_id}): the server restarted without it (no persistence, or writes lost in a crash); "
                "resynchronise: read the current state, then watch from the current revision"
            )
        return sub.add_watch(watch_id, filters, dict(start_revisions or {}), latest)

    def take(self, sub: Subscription, max_events: int = 0, max_bytes: int = 0) -> list[Match]:
        """The events pending for ``sub`` (:meth:`Subscription.poll`), counted as delivered to this caller.

        The transports hand what this returns to the watcher at once (encoded
        into the stream's next message, or to the in-process sink), so this is
        the moment the delivery latency is taken (docs/experiments.md).
        """
        matches = sub.poll(max_events, max_bytes)
        if matches and self._metrics is not None:
            self._metrics.delivered(self.who, sub, matches, self.carries_entry)
        return matches

    def carries_entry(self, match: Match) -> bool:
        """Whether an event goes to this caller with its entry: asked for, and not under another's ODR lock."""
        holder = match.event.odr_holder
        return match.include_entry and (holder is None or holder == self.who.component_id)

    # ---------------------------------------------------------- shared memory
    # Large values on one host (cast.core.shared): a write may name its bytes in the writer's staging area, and a
    # read for a session may get values lent by reference.

    def staged(
        self, session_id: bytes, offset: int, size: int, entry_id: str
    ) -> tuple[bytes | memoryview, Placed | None]:
        """The bytes a write staged in the caller's session, copied into the server's shared memory."""
        shared = self.system.shared
        if shared is None:
            raise InvalidArgumentError(
                f"the value of entry '{entry_id}' is staged in shared memory, which this server has turned off "
                "(shared_memory.enabled: false): send the value's bytes (value.value)"
            )
        return shared.staged(self.who, session_id, offset, size, entry_id)

    def lend(self, session: SharedSession, call: int, held: object) -> Lent | None:
        """Lend a record's value (its ``shared``) to the caller's ``session`` on ``call``; None: send its bytes."""
        shared = self.system.shared
        if shared is None or not isinstance(held, Placed):
            return None
        return shared.lend(session, call, held)

    # ---------------------------------------------------------------- helpers

    def _settled(self, call: Callable[[], T]) -> Steps[T]:
        refused: CastError | None = None
        try:
            result = call()
        except CastError as exc:
            refused = exc
        if refused is not None:  # yielded outside the handler (mypyc)
            yield DURABLE  # a refusal names versions and holders: only durable ones
            raise refused
        yield DURABLE
        return result


def event_for(access: Access, match: Match) -> ChangeEvent:
    """The event as this caller may see it: without its entry unless :meth:`Access.carries_entry`."""
    ev = match.event
    carries = ev.entry is None or access.carries_entry(match)
    if carries and not match.skipped:
        return ev
    copy = ChangeEvent(ev.seq, ev.revision, ev.operation, ev.subarchitecture, ev.id, ev.type, ev.source_component,
                       ev.source_subarchitecture, ev.version, ev.time_ns, ev.entry if carries else None,
                       ev.odr_holder)
    copy.skipped, copy.first_skipped_revision = match.skipped, match.first_skipped
    return copy


# ------------------------------------------------------------------ drivers


def run_sync(system: System, steps: Steps[T], timeout: float | None = None) -> T:
    """Drive ``steps`` on this thread; a lock wait gives up after ``timeout`` seconds."""
    end = None if timeout is None else time.monotonic() + timeout
    journal = system.journal if system.journal is not None and system.journal.waits else None
    try:
        step = next(steps)
        while True:
            if step is DURABLE:
                if journal is not None:
                    journal.wait(journal.ticket())
                step = steps.send(None)
                continue
            assert isinstance(step, Unlocked)
            released = threading.Event()
            cancel = system.host.wait_for_unlock(step.sa, step.entry_id, released.set)
            try:
                in_time = released.wait(None if end is None else max(0.0, end - time.monotonic()))
            finally:
                cancel()
            step = steps.send(None) if in_time else steps.throw(_too_late(step))
    except StopIteration as done:
        return done.value  # type: ignore[no-any-return]


def _too_late(step: Unlocked) -> DeadlineExceededError:
    """The error of a lock wait that ran out of time."""
    return DeadlineExceededError(f"deadline passed while waiting: {step.blocked.message}")


async def run_async(system: System, steps: Steps[T], timeout: float | None = None) -> T:
    """Drive ``steps`` on the running event loop; a lock wait gives up after ``timeout`` seconds."""
    try:
        step = next(steps)
    except StopIteration as done:
        return done.value  # type: ignore[no-any-return]
    return await resume_async(system, steps, step, timeout)


def settle_at_once(
    system: System, steps: Steps[T], step: Durable | Unlocked
) -> tuple[Durable | Unlocked | None, T | None]:
    """Take the steps that need no waiting: durability when nothing waits for the journal.

    Returns ``(None, result)`` once done (the common case without a waiting
    journal, where an event-loop round trip per call would only add latency),
    or ``(step, None)`` with the step still to be awaited (:func:`resume_async`).
    Errors the steps raise are raised.
    """
    while step is DURABLE and system.durable_at_once:
        try:
            step = steps.send(None)
        except StopIteration as done:
            return None, done.value
    return step, None


async def resume_async(system: System, steps: Steps[T], step: Durable | Unlocked, timeout: float | None = None) -> T:
    """:func:`run_async` from a step the caller already took (``next(steps)`` returned ``step``)."""
    loop = asyncio.get_running_loop()
    end = None if timeout is None else loop.time() + timeout
    try:
        while True:
            if step is DURABLE:
                await system.durable()
                late = None
            else:
                assert isinstance(step, Unlocked)
                late = await _wait_unlocked(system, step, None if end is None else max(0.0, end - loop.time()))
            step = steps.send(None) if late is None else steps.throw(late)
    except StopIteration as done:
        return done.value  # type: ignore[no-any-return]


async def _wait_unlocked(system: System, step: Unlocked, timeout: float | None) -> DeadlineExceededError | None:
    """Wait on the event loop until ``step``'s entry is released; the error to throw if ``timeout`` ran out."""
    loop = asyncio.get_running_loop()
    released: asyncio.Future[None] = loop.create_future()

    def resolve() -> None:
        if not released.done():
            released.set_result(None)

    def wake() -> None:
        loop.call_soon_threadsafe(resolve)  # the releasing thread is not the loop's

    cancel = system.host.wait_for_unlock(step.sa, step.entry_id, wake)
    try:
        await asyncio.wait_for(released, timeout=timeout)
        return None
    except TimeoutError:
        return _too_late(step)
    finally:
        cancel()

