"""The WM core: every working memory of one server, and every guarantee of docs/design.md section 4.

:class:`MemoryHost` is plain Python with no gRPC in it. Its public methods are
called from the server's servicers (on the event loop) and directly from
in-process components (on their own threads), so all state is guarded by one
mutex, held only for the dictionary work of a call. Waiting (for a lock, for
new events) never happens under the mutex: the host calls back listeners after
the mutex is released, and the caller decides how to wait (asyncio or thread).

With a journal that writers wait for (``always``, ``batch``), a write is
committed in two steps: under the mutex it is checked against the latest
state, numbered and queued for the journal (it is then *pending*); once the
journal has made it durable, :meth:`MemoryHost.apply_durable` moves it into
the visible state that reads, watchers and task policies see. So nobody
observes a write that a crash could undo (see :mod:`cast.core.memory`).
Calls that check the latest state (writes, locks) answer only once it is
durable; the transports wait for that (:meth:`cast.core.system.System.settle`).

The checks of a write, and their order, are in :mod:`cast.core.planning`.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence

from cast.core.checks import check_id, check_sa_name, locked_message, missing_message
from cast.core.locks import Locking
from cast.core.memory import Pending, WorkingMemory
from cast.core.planning import Overlay, Planned, ValueValidator, WritePlanner
from cast.core.records import (
    BatchOp,
    ChangeEvent,
    EntryRecord,
    Identity,
    Limits,
    LockMode,
    Operation,
    Quota,
    WriteResult,
)
from cast.core.room import Room, Tally
from cast.errors import CastError, InvalidArgumentError, LockedError, NotFoundError

__all__ = ["BatchOp", "MemoryHost", "ValueValidator"]

log = logging.getLogger("cast.host")


class MemoryHost(Locking):
    """Working memories of several subarchitectures behind one mutex."""

    def __init__(
        self,
        subarchitectures: Iterable[str],
        limits: Limits | None = None,
        validator: ValueValidator | None = None,
        clock: Callable[[], int] = time.time_ns,
        version_floor: int = 0,
        quotas: Mapping[str, Quota] | None = None,
    ) -> None:
        self.limits = limits or Limits()
        self._clock = clock
        room = Room(self.limits, quotas or {}, self._usage_locked)
        self._planner = WritePlanner(self.limits, validator, clock, version_floor, room)
        self._mutex = threading.Lock()
        self._wms: dict[str, WorkingMemory] = {}
        for name in subarchitectures:
            check_sa_name(name)
            if name in self._wms:
                raise InvalidArgumentError(f"subarchitecture '{name}' is named twice")
            self._wms[name] = WorkingMemory(name, self.limits.history_events, self.limits.history_bytes)
        self._seq = itertools.count(1)
        self._seq_floor = 0  # highest event sequence number restored from a journal
        self._listeners: list[Callable[[], None]] = []
        self._watchers = 0  # listeners that are watchers (limits.max_watchers)
        self._init_locks()
        # Called under the mutex with the events of each commit (cast.core.journal.Journal.append):
        # it only queues them, so durability never holds the mutex for I/O. None: memory only.
        self.journal: Callable[[list[ChangeEvent]], None] | None = None
        # True while writes become visible only once the journal made them durable (apply_durable).
        self.deferred = False

    def attach_journal(self, append: Callable[[list[ChangeEvent]], None], deferred: bool) -> None:
        """Journal every commit from now on; ``deferred``: show a write only once it is durable.

        With ``deferred`` the journal must call :meth:`apply_durable` with the
        events of every commit it made durable, in the order it was given them.
        """
        with self._mutex:
            self.journal = append
            self.deferred = deferred

    def detach_journal(self) -> None:
        """Stop journaling (the journal is closing: it has applied everything it was given)."""
        with self._mutex:
            self.journal = None
            self.deferred = False

    @property
    def version_floor(self) -> int:
        """The lowest version any write of this run may give (cast.core.versions)."""
        return self._planner.version_floor

    # ----------------------------------------------------------------- queries

    @property
    def subarchitectures(self) -> list[str]:
        """Names of the hosted SAs, in configuration order."""
        return list(self._wms)

    def revision(self, sa: str) -> int:
        """Visible revision of one WM."""
        return self._wm(sa).revision

    def revisions(self) -> dict[str, int]:
        """Visible revision of every WM."""
        with self._mutex:
            return {name: wm.revision for name, wm in self._wms.items()}

    def entry_count(self, sa: str) -> int:
        """Number of visible entries in one WM."""
        return len(self._wm(sa).entries)

    def usage(self, sa: str = "") -> dict[str, tuple[int, int]]:
        """(entries, bytes) each component holds in one WM (default: all), in the latest state."""
        with self._mutex:
            if sa:
                return {author: (e, b) for author, (e, b) in self._wm(sa).usage.items()}
            return {author: (e, b) for author, (e, b) in self._usage_locked().items()}

    def total_bytes(self, sa: str) -> int:
        """Bytes of values and ids one WM holds in the latest state (limits.max_total_bytes)."""
        with self._mutex:
            return self._wm(sa).total_bytes

    def shared_bytes(self, sa: str) -> int:
        """Bytes of the visible values of one WM kept in shared memory (cast.core.shared)."""
        with self._mutex:
            return sum(len(r.data) for r in self._wm(sa).entries.values() if r.shared is not None)

    def _usage_locked(self) -> dict[str, list[int]]:
        total: dict[str, list[int]] = {}
        for wm in self._wms.values():
            for author, (entries, size) in wm.usage.items():
                held = total.setdefault(author, [0, 0])
                held[0] += entries
                held[1] += size
        return total

    def pending_writes(self, sa: str = "") -> int:
        """Writes of one WM (default: all) committed in memory and waiting for the journal (0 unless deferred)."""
        with self._mutex:
            wms = [self._wm(sa)] if sa else self._wms.values()
            return sum(wm.assigned - wm.revision for wm in wms)

    def type_counts(self, sa: str) -> dict[str, int]:
        """Visible entries per type in one WM."""
        with self._mutex:
            return self._wm(sa).type_counts()

    # ------------------------------------------------------------------ reads
    # Reads see the visible state only: nothing a crash could undo.

    def get(self, who: Identity, sa: str, entry_id: str) -> EntryRecord:
        """Read one entry. NOT_FOUND if missing, FAILED_PRECONDITION if ODR-locked by another."""
        check_id(entry_id, self.limits)
        with self._mutex:
            wm = self._wm(sa)
            record = wm.entries.get(entry_id)
            if record is None:
                raise NotFoundError(missing_message(sa, entry_id))
            lock = wm.locks.get(entry_id)
            if lock is not None and lock.mode is LockMode.ODR and lock.holder != who.component_id:
                raise LockedError(locked_message(sa, entry_id, lock, "read"))
            return record

    def get_by_type(self, who: Identity, sa: str, type_name: str, limit: int = 0) -> tuple[list[EntryRecord], int]:
        """Entries of one type, newest first, and the revision read.

        Entries that another component holds ODR-locked are left out: a type
        read must not fail because one entry of many is being modified.
        """
        if not type_name:
            raise InvalidArgumentError(
                "no type to read: give the full message name of the entries (GetByType's type field, "
                "e.g. 'google.protobuf.StringValue')"
            )
        self._planner.check_type(type_name)
        if limit < 0:
            raise InvalidArgumentError(f"limit must be 0 (no cap) or positive, got {limit}")
        with self._mutex:
            wm = self._wm(sa)
            if not wm.locks:
                return list(wm.newest_of_type(type_name, limit)), wm.revision
            out: list[EntryRecord] = []
            for record in wm.newest_of_type(type_name):
                lock = wm.locks.get(record.id)
                if lock is not None and lock.mode is LockMode.ODR and lock.holder != who.component_id:
                    continue
                out.append(record)
                if limit and len(out) >= limit:
                    break
            return out, wm.revision

    def exists(self, who: Identity, sa: str, entry_id: str) -> bool:
        """Whether the entry exists (existence is not content: no ODR check)."""
        check_id(entry_id, self.limits)
        with self._mutex:
            return entry_id in self._wm(sa).entries

    def all_entries(self, sa: str) -> list[EntryRecord]:
        """Every entry of one WM, oldest write first (tools and persistence)."""
        with self._mutex:
            return sorted(self._wm(sa).entries.values(), key=lambda r: r.revision)

    # ----------------------------------------------------------------- writes

    def add(self, who: Identity, sa: str, entry_id: str, type_name: str, data: bytes) -> WriteResult:
        """Create an entry: version 0, or last version + 1 after a delete."""
        return self.write(who, BatchOp(Operation.ADD, sa, entry_id, type_name, data))

    def overwrite(
        self,
        who: Identity,
        sa: str,
        entry_id: str,
        type_name: str,
        data: bytes,
        expected_version: int | None = None,
    ) -> WriteResult:
        """Replace an entry's value; version + 1."""
        return self.write(who, BatchOp(Operation.OVERWRITE, sa, entry_id, type_name, data, expected_version))

    def delete(self, who: Identity, sa: str, entry_id: str, expected_version: int | None = None) -> WriteResult:
        """Delete an entry and release every lock on it."""
        return self.write(who, BatchOp(Operation.DELETE, sa, entry_id, expected_version=expected_version))

    def batch(self, who: Identity, ops: Sequence[BatchOp]) -> list[WriteResult]:
        """Apply writes in order, all or nothing.

        Every operation is checked against the state the earlier ones leave
        behind before any is applied, so a failure changes nothing; the error
        names the failing operation's index.
        """
        if len(ops) > self.limits.max_batch_operations:
            raise InvalidArgumentError(
                f"batch has {len(ops)} operations, over the limit of {self.limits.max_batch_operations}: "
                "split it into several batches"
            )
        for op in ops:
            self._planner.check_args(op)
        with self._mutex:
            overlay: Overlay = {}
            tally = Tally()
            planned = []
            now = self._clock()  # the operations of one batch share their time
            for index, op in enumerate(ops):
                try:
                    planned.append(self._planner.plan(self._wm(op.subarchitecture), who, op, overlay, tally, now))
                except CastError as exc:
                    exc.message = f"batch operation {index}: {exc.message}"
                    exc.args = (exc.message,)
                    raise
            results, released = self._commit(planned)
        self._after_commit(released)
        return results

    def write(self, who: Identity, op: BatchOp) -> WriteResult:
        """Apply one write (add, overwrite or delete) described by ``op``."""
        self._planner.check_args(op)
        with self._mutex:
            planned = self._planner.plan(self._wm(op.subarchitecture), who, op, None, None)
            results, released = self._commit([planned])
        self._after_commit(released)
        return results[0]

    def _commit(self, planned: list[Planned]) -> tuple[list[WriteResult], list[tuple[str, str]]]:
        results = []
        released: list[tuple[str, str]] = []
        journal = self.journal
        deferred = self.deferred
        journaled: list[ChangeEvent] = []
        for p in planned:
            wm = p.wm
            revision = wm.assigned = wm.assigned + 1
            entry_id = (p.record or p.old).id  # type: ignore[union-attr]
            wm.account(p.old, p.record)
            lock = wm.locks.get(entry_id)
            odr_holder = lock.holder if lock is not None and lock.mode is LockMode.ODR else None
            seq = next(self._seq)
            if p.record is not None:
                record = p.record
                record.revision = revision
                event_entry = record
                time_ns = record.modified_ns
                if deferred:
                    wm.pending[entry_id] = Pending(record, None, seq)
                    wm.pending_delta += p.op is Operation.ADD
                else:
                    wm.put(record)
            else:
                event_entry = p.old  # type: ignore[assignment]
                time_ns = self._clock()
                if deferred:
                    wm.pending[entry_id] = Pending(None, event_entry.version, seq)
                    wm.pending_delta -= 1
                else:
                    wm.remove(entry_id)
                # Locks follow the latest state: the delete releases them now, durable or not.
                if lock is not None:
                    del wm.locks[entry_id]
                    self._forget_lock(lock.holder, wm.name, entry_id)
                    released.append((wm.name, entry_id))
            event = ChangeEvent(
                seq,
                revision,
                p.op,
                wm.name,
                entry_id,
                event_entry.type,
                p.who.component_id,
                p.who.subarchitecture,
                event_entry.version,
                time_ns,
                event_entry,
                odr_holder,
            )
            if not deferred:
                wm.history.append(event)
            if journal is not None:
                journaled.append(event)
            results.append(WriteResult(revision, event_entry.version))
        if journal is not None:
            journal(journaled)
        return results, released

    def _after_commit(self, released: list[tuple[str, str]]) -> None:
        if not self.deferred:
            self._notify()
        for key in released:
            self._wake_lock_waiters(key)

    def _notify(self) -> None:
        for listener in list(self._listeners):
            try:
                listener()
            except Exception:  # one broken watcher must not stop the writer or the journal
                log.exception("a change listener failed")

    def apply_durable(self, events: Sequence[ChangeEvent]) -> None:
        """Make writes visible that the journal has made durable (in commit order).

        Called by the journal's committer thread before it releases the
        writers waiting for these events; watchers are woken on that thread.
        """
        with self._mutex:
            for event in events:
                wm = self._wms[event.subarchitecture]
                if event.operation is Operation.DELETE:
                    wm.remove(event.id)
                    wm.pending_delta += 1
                else:
                    assert event.entry is not None  # the host always keeps the record with the event
                    wm.put(event.entry)
                    wm.pending_delta -= event.operation is Operation.ADD
                wm.history.append(event)
                latest = wm.pending.get(event.id)
                if latest is not None and latest.seq == event.seq:
                    del wm.pending[event.id]
        self._notify()

    def system_write(self, author: Identity, op: BatchOp) -> WriteResult:
        """A write by the server itself (task records): no permission or lock checks."""
        privileged = Identity(author.component_id, author.subarchitecture, True)
        with self._mutex:
            wm = self._wm(op.subarchitecture)
            saved = wm.locks.pop(op.id, None)
            try:
                planned = self._planner.plan(wm, privileged, op, None, None, system=True)
            finally:
                if saved is not None:
                    wm.locks[op.id] = saved
            results, released = self._commit([planned])
        self._after_commit(released)
        return results[0]

    def restore(
        self,
        sa: str,
        entries: Sequence[EntryRecord],
        deleted: dict[str, int],
        revision: int,
        events: Sequence[ChangeEvent],
    ) -> None:
        """Load one WM's state read back from a journal, before the host serves anyone.

        ``entries`` oldest write first (so the type index is newest first again),
        ``deleted`` the last versions of deleted entries, ``revision`` the WM's
        revision counter, ``events`` the newest events kept (contiguous up to
        ``revision``; otherwise the history restarts empty after ``revision``).
        """
        with self._mutex:
            wm = self._wm(sa)
            for record in entries:
                wm.put(record)
                wm.account(None, record)
            wm.last_versions.update(deleted)
            kept = list(events)
            contiguous = bool(kept) and kept[-1].revision == revision and all(
                b.revision == a.revision + 1 for a, b in itertools.pairwise(kept)
            )
            wm.history.reset((kept[0].revision - 1) if contiguous else revision)
            for event in kept if contiguous else ():
                wm.history.append(event)
            wm.assigned = revision
            top = max((e.seq for e in kept), default=0)
            self._seq = itertools.count(max(top, self._seq_floor) + 1)
            self._seq_floor = max(top, self._seq_floor)

    # -------------------------------------------------------------- watching

    def add_listener(self, listener: Callable[[], None], watcher: bool = True) -> None:
        """Call ``listener()`` whenever writes become visible (no mutex held).

        It runs on the writer's thread, or with a deferring journal on the
        journal's committer thread, so it must only wake someone, never block.
        ``watcher``: it counts against ``limits.max_watchers``.
        """
        with self._mutex:
            self._listeners.append(listener)
            self._watchers += watcher

    def remove_listener(self, listener: Callable[[], None], watcher: bool = True) -> None:
        """Stop calling a listener added by :meth:`add_listener`."""
        with self._mutex:
            try:
                self._listeners.remove(listener)
            except ValueError:
                return
            self._watchers -= watcher

    def listener_count(self) -> int:
        """Number of registered watchers (watch streams and in-process watchers)."""
        return self._watchers

    def events_since(self, sa: str, next_revision: int) -> list[ChangeEvent]:
        """Events of one WM from ``next_revision`` on; HistoryExpiredError if some are gone."""
        with self._mutex:
            return self._wm(sa).history.since(next_revision)

    def history_bounds(self, sa: str) -> tuple[int, int]:
        """(first, last) revision kept in one WM's history."""
        with self._mutex:
            h = self._wm(sa).history
            return h.first, h.last

    # ---------------------------------------------------------------- checks

    def _wm(self, sa: str) -> WorkingMemory:
        wm = self._wms.get(sa)
        if wm is None:
            known = ", ".join(sorted(self._wms)) or "none"
            raise NotFoundError(f"no subarchitecture '{sa}' on this server (known: {known})")
        return wm
