"""The WM core: every working memory of one server, and every guarantee of DESIGN.md section 4.

:class:`MemoryHost` is plain Python with no gRPC in it. Its public methods are
called from the server's servicers (on the event loop) and directly from
in-process components (on their own threads), so all state is guarded by one
mutex, held only for the dictionary work of a call. Waiting (for a lock, for
new events) never happens under the mutex: the host calls back listeners after
the mutex is released, and the caller decides how to wait (asyncio or thread).

Order of checks for a write, so that the most useful error wins and a failed
call changes nothing: arguments (INVALID_ARGUMENT), subarchitecture
(NOT_FOUND), permission (PERMISSION_DENIED), existence (NOT_FOUND /
ALREADY_EXISTS), lock (FAILED_PRECONDITION), version (ABORTED), limits
(RESOURCE_EXHAUSTED), value schema (INVALID_ARGUMENT).
"""

from __future__ import annotations

import itertools
import re
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple

from cast.core.memory import LockState, WorkingMemory
from cast.core.records import ChangeEvent, EntryRecord, Identity, Limits, LockMode, Operation, WriteResult
from cast.errors import (
    AlreadyExistsError,
    CastError,
    ConsistencyError,
    InvalidArgumentError,
    LockedError,
    NotFoundError,
    PermissionDeniedError,
    ResourceExhaustedError,
)

__all__ = ["BatchOp", "MemoryHost", "ValueValidator"]

ValueValidator = Callable[[str, bytes], None]
"""Called with (type, bytes) before a write; raises InvalidArgumentError if the bytes do not parse."""

_TYPE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*\Z")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


class BatchOp(NamedTuple):
    """One write of a batch: ``data``/``type`` are ignored for DELETE."""

    operation: Operation
    subarchitecture: str
    id: str
    type: str = ""
    data: bytes = b""
    expected_version: int | None = None


class _Planned:
    """A write that passed every check, ready to be committed."""

    __slots__ = ("old", "op", "record", "who", "wm")

    def __init__(
        self, wm: WorkingMemory, op: Operation, record: EntryRecord | None, old: EntryRecord | None, who: Identity
    ) -> None:
        self.wm = wm
        self.op = op
        self.record = record  # new record (revision filled at commit); None for DELETE
        self.old = old
        self.who = who


class _Slot(NamedTuple):
    """State of one address after the earlier operations of a batch."""

    record: EntryRecord | None  # None: deleted in this batch
    deleted_version: int | None  # version it had when deleted


class MemoryHost:
    """Working memories of several subarchitectures behind one mutex."""

    def __init__(
        self,
        subarchitectures: Iterable[str],
        limits: Limits | None = None,
        validator: ValueValidator | None = None,
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self.limits = limits or Limits()
        self._validator = validator
        self._clock = clock
        self._mutex = threading.Lock()
        self._wms: dict[str, WorkingMemory] = {}
        for name in subarchitectures:
            _check_sa_name(name)
            if name in self._wms:
                raise InvalidArgumentError(f"subarchitecture '{name}' is named twice")
            self._wms[name] = WorkingMemory(name, self.limits.history_events, self.limits.history_bytes)
        self._seq = itertools.count(1)
        self._seq_floor = 0  # highest event sequence number restored from a journal
        self._listeners: list[Callable[[], None]] = []
        self._lock_waiters: dict[tuple[str, str], list[Callable[[], None]]] = {}
        self._waiter_count = 0
        self._held: dict[str, set[tuple[str, str]]] = {}  # component -> locked addresses
        self._good_types: set[str] = set()  # type names that passed _check_type
        # Called under the mutex with the events of each commit (cast.core.journal.Journal.append):
        # it only queues them, so durability never holds the mutex for I/O. None: memory only.
        self.journal: Callable[[list[ChangeEvent]], None] | None = None

    # ----------------------------------------------------------------- queries

    @property
    def subarchitectures(self) -> list[str]:
        """Names of the hosted SAs, in configuration order."""
        return list(self._wms)

    def revision(self, sa: str) -> int:
        """Current revision of one WM."""
        return self._wm(sa).revision

    def revisions(self) -> dict[str, int]:
        """Current revision of every WM."""
        with self._mutex:
            return {name: wm.revision for name, wm in self._wms.items()}

    def entry_count(self, sa: str) -> int:
        """Number of entries in one WM."""
        return len(self._wm(sa).entries)

    def type_counts(self, sa: str) -> dict[str, int]:
        """Entries per type in one WM."""
        with self._mutex:
            return self._wm(sa).type_counts()

    # ------------------------------------------------------------------ reads

    def get(self, who: Identity, sa: str, entry_id: str) -> EntryRecord:
        """Read one entry. NOT_FOUND if missing, FAILED_PRECONDITION if ODR-locked by another."""
        self._check_id(entry_id)
        with self._mutex:
            wm = self._wm(sa)
            record = wm.entries.get(entry_id)
            if record is None:
                raise NotFoundError(_missing(sa, entry_id))
            lock = wm.locks.get(entry_id)
            if lock is not None and lock.mode is LockMode.ODR and lock.holder != who.component_id:
                raise LockedError(_locked_msg(sa, entry_id, lock, "read"))
            return record

    def get_by_type(self, who: Identity, sa: str, type_name: str, limit: int = 0) -> tuple[list[EntryRecord], int]:
        """Entries of one type, newest first, and the revision read.

        Entries that another component holds ODR-locked are left out: a type
        read must not fail because one entry of many is being modified.
        """
        self._check_type(type_name)
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
        self._check_id(entry_id)
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
            self._check_args(op)
        with self._mutex:
            overlay: dict[tuple[str, str], _Slot] = {}
            counts: dict[str, int] = {}
            planned = []
            now = self._clock()  # the operations of one batch share their time
            for index, op in enumerate(ops):
                try:
                    planned.append(self._plan(who, op, overlay, counts, now))
                except CastError as exc:
                    exc.message = f"batch operation {index}: {exc.message}"
                    exc.args = (exc.message,)
                    raise
            results, released = self._commit(planned)
        self._after_commit(released)
        return results

    def write(self, who: Identity, op: BatchOp) -> WriteResult:
        """Apply one write (add, overwrite or delete) described by ``op``."""
        self._check_args(op)
        with self._mutex:
            planned = self._plan(who, op, None, None)
            results, released = self._commit([planned])
        self._after_commit(released)
        return results[0]

    def _check_args(self, op: BatchOp) -> None:
        self._check_id(op.id)
        if op.operation is not Operation.DELETE:
            self._check_type(op.type)
            if len(op.data) > self.limits.max_value_bytes:
                raise InvalidArgumentError(
                    f"value of entry '{op.id}' is {len(op.data)} bytes, over the limit of "
                    f"{self.limits.max_value_bytes} bytes (limits.max_value_bytes): store large data "
                    "elsewhere and keep a reference, or raise the limit in the configuration"
                )
        if op.expected_version is not None and op.expected_version < 0:
            raise InvalidArgumentError(f"expected_version must be >= 0, got {op.expected_version}")

    def _plan(
        self,
        who: Identity,
        op: BatchOp,
        overlay: dict[tuple[str, str], _Slot] | None,
        counts: dict[str, int] | None,
        now: int = 0,
    ) -> _Planned:
        wm = self._wm(op.subarchitecture)
        sa, entry_id = op.subarchitecture, op.id
        if sa != who.subarchitecture and not who.privileged:
            raise PermissionDeniedError(
                f"{who.describe()} may not {op.operation.name.lower()} in subarchitecture '{sa}': "
                "only privileged components write outside their own SA (set privileged: true in the "
                "configuration if this component coordinates other SAs)"
            )
        key = (sa, entry_id)
        slot = overlay.get(key) if overlay is not None else None
        current = slot.record if slot is not None else wm.entries.get(entry_id)
        lock = wm.locks.get(entry_id)
        if slot is not None and slot.record is None:
            lock = None  # deleted earlier in this batch: its lock went with it
        now = now or self._clock()
        if op.operation is Operation.ADD:
            if current is not None:
                raise AlreadyExistsError(
                    f"entry '{entry_id}' already exists in subarchitecture '{sa}' (version {current.version}, "
                    f"type {current.type}): use overwrite to change it, or new_id() for a fresh id"
                )
            delta = counts.get(sa, 0) if counts is not None else 0
            if len(wm.entries) + delta >= self.limits.max_entries:
                raise ResourceExhaustedError(
                    f"subarchitecture '{sa}' holds {len(wm.entries) + delta} entries, the limit "
                    f"(limits.max_entries = {self.limits.max_entries}): delete entries or raise the limit"
                )
            if self._validator is not None:
                self._validator(op.type, op.data)
            prev = slot.deleted_version if slot is not None else wm.last_versions.get(entry_id)
            version = 0 if prev is None else prev + 1
            record = EntryRecord(sa, entry_id, op.type, op.data, version, who.component_id, now, 0)
            planned = _Planned(wm, Operation.ADD, record, None, who)
            if counts is not None:
                counts[sa] = delta + 1
        else:
            if current is None:
                raise NotFoundError(_missing(sa, entry_id) + f": cannot {op.operation.name.lower()} it")
            if lock is not None and lock.holder != who.component_id:
                if op.operation is Operation.OVERWRITE or lock.mode is not LockMode.O:
                    raise LockedError(_locked_msg(sa, entry_id, lock, op.operation.name.lower()))
            if op.expected_version is not None and op.expected_version != current.version:
                raise ConsistencyError(
                    f"entry '{entry_id}' in subarchitecture '{sa}' is at version {current.version}, "
                    f"expected {op.expected_version}: it was changed by '{current.author}'; read it again "
                    "and retry"
                )
            if op.operation is Operation.OVERWRITE:
                if self._validator is not None:
                    self._validator(op.type, op.data)
                record = EntryRecord(sa, entry_id, op.type, op.data, current.version + 1, who.component_id, now, 0)
                planned = _Planned(wm, Operation.OVERWRITE, record, current, who)
            else:
                planned = _Planned(wm, Operation.DELETE, None, current, who)
                if counts is not None:
                    counts[sa] = counts.get(sa, 0) - 1
        if overlay is not None:
            deleted = current.version if planned.record is None and current is not None else None
            overlay[key] = _Slot(planned.record, deleted)
        return planned

    def _commit(self, planned: list[_Planned]) -> tuple[list[WriteResult], list[tuple[str, str]]]:
        results = []
        released: list[tuple[str, str]] = []
        journal = self.journal
        journaled: list[ChangeEvent] = []
        for p in planned:
            wm = p.wm
            revision = wm.revision + 1
            entry_id = (p.record or p.old).id  # type: ignore[union-attr]
            lock = wm.locks.get(entry_id)
            odr_holder = lock.holder if lock is not None and lock.mode is LockMode.ODR else None
            if p.record is not None:
                record = p.record
                record.revision = revision
                wm.put(record)
                event_entry = record
                version = record.version
            else:
                old = wm.remove(entry_id)
                if lock is not None:
                    self._forget_lock(lock.holder, wm.name, entry_id)
                    released.append((wm.name, entry_id))
                event_entry = old
                version = old.version
            event = ChangeEvent(
                next(self._seq),
                revision,
                p.op,
                wm.name,
                entry_id,
                event_entry.type,
                p.who.component_id,
                p.who.subarchitecture,
                version,
                event_entry.modified_ns if p.record is not None else self._clock(),
                event_entry,
                odr_holder,
            )
            wm.history.append(event)
            if journal is not None:
                journaled.append(event)
            results.append(WriteResult(revision, version))
        if journal is not None:
            journal(journaled)
        return results, released

    def _after_commit(self, released: list[tuple[str, str]]) -> None:
        for listener in list(self._listeners):
            listener()
        for key in released:
            self._wake_lock_waiters(key)

    def system_write(self, author: Identity, op: BatchOp) -> WriteResult:
        """A write by the server itself (task records): no permission or lock checks."""
        privileged = Identity(author.component_id, author.subarchitecture, True)
        with self._mutex:
            wm = self._wm(op.subarchitecture)
            saved = wm.locks.pop(op.id, None)
            try:
                planned = self._plan(privileged, op, None, None)
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
            wm.last_versions.update(deleted)
            kept = list(events)
            contiguous = bool(kept) and kept[-1].revision == revision and all(
                b.revision == a.revision + 1 for a, b in itertools.pairwise(kept)
            )
            wm.history.reset((kept[0].revision - 1) if contiguous else revision)
            for event in kept if contiguous else ():
                wm.history.append(event)
            top = max((e.seq for e in kept), default=0)
            self._seq = itertools.count(max(top, self._seq_floor) + 1)
            self._seq_floor = max(top, self._seq_floor)

    # ------------------------------------------------------------------ locks

    def try_lock(self, who: Identity, sa: str, entry_id: str, mode: LockMode) -> int:
        """Take (or re-enter) a lock at once; return the depth. FAILED_PRECONDITION if held by another.

        Re-entering keeps the stronger of the held and requested modes.
        """
        self._check_id(entry_id)
        mode = LockMode(mode)
        with self._mutex:
            wm = self._wm(sa)
            if entry_id not in wm.entries:
                raise NotFoundError(_missing(sa, entry_id) + ": cannot lock it")
            lock = wm.locks.get(entry_id)
            if lock is None:
                wm.locks[entry_id] = LockState(who.component_id, mode)
                self._held.setdefault(who.component_id, set()).add((sa, entry_id))
                return 1
            if lock.holder != who.component_id:
                raise LockedError(_locked_msg(sa, entry_id, lock, "lock"))
            lock.depth += 1
            lock.mode = max(lock.mode, mode)
            return lock.depth

    def unlock(self, who: Identity, sa: str, entry_id: str) -> int:
        """Release one level of the caller's lock; return the remaining depth."""
        self._check_id(entry_id)
        with self._mutex:
            wm = self._wm(sa)
            if entry_id not in wm.entries:
                raise NotFoundError(_missing(sa, entry_id) + ": cannot unlock it")
            lock = wm.locks.get(entry_id)
            if lock is None:
                raise LockedError(f"entry '{entry_id}' in subarchitecture '{sa}' is not locked: nothing to unlock")
            if lock.holder != who.component_id:
                raise LockedError(
                    f"entry '{entry_id}' in subarchitecture '{sa}' is locked by '{lock.holder}', not by "
                    f"{who.describe()}: only the holder may unlock it"
                )
            lock.depth -= 1
            if lock.depth > 0:
                return lock.depth
            del wm.locks[entry_id]
            self._forget_lock(who.component_id, sa, entry_id)
        self._wake_lock_waiters((sa, entry_id))
        return 0

    def lock_holder(self, sa: str, entry_id: str) -> tuple[str, LockMode, int] | None:
        """(holder, mode, depth) of the lock on an entry, or None."""
        with self._mutex:
            lock = self._wm(sa).locks.get(entry_id)
            return None if lock is None else (lock.holder, lock.mode, lock.depth)

    def locks_of(self, component_id: str) -> list[tuple[str, str]]:
        """Addresses the component holds locks on."""
        with self._mutex:
            return sorted(self._held.get(component_id, ()))

    def release_component(self, component_id: str) -> list[tuple[str, str]]:
        """Release every lock a component holds (its session ended); return the addresses."""
        with self._mutex:
            keys = sorted(self._held.pop(component_id, ()))
            for sa, entry_id in keys:
                self._wms[sa].locks.pop(entry_id, None)
        for key in keys:
            self._wake_lock_waiters(key)
        return keys

    def _forget_lock(self, holder: str, sa: str, entry_id: str) -> None:
        held = self._held.get(holder)
        if held is not None:
            held.discard((sa, entry_id))
            if not held:
                del self._held[holder]

    def wait_for_unlock(self, sa: str, entry_id: str, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback`` once when the entry's lock is released (or the entry deleted).

        Returns a function that cancels the wait. RESOURCE_EXHAUSTED past
        ``limits.max_lock_waiters``. The callback runs on the releasing thread
        with no mutex held; it should only wake the waiter, which then retries.
        """
        key = (sa, entry_id)
        with self._mutex:
            if self._waiter_count >= self.limits.max_lock_waiters:
                raise ResourceExhaustedError(
                    f"{self._waiter_count} lock waiters are pending, the limit (limits.max_lock_waiters = "
                    f"{self.limits.max_lock_waiters}): use try_lock, or raise the limit"
                )
            self._lock_waiters.setdefault(key, []).append(callback)
            self._waiter_count += 1
            lock = self._wms[sa].locks.get(entry_id) if sa in self._wms else None
        if lock is None:
            # Released between the caller's try and this registration: wake at once.
            self._wake_lock_waiters(key)

        def cancel() -> None:
            with self._mutex:
                waiters = self._lock_waiters.get(key)
                if waiters is not None and callback in waiters:
                    waiters.remove(callback)
                    self._waiter_count -= 1
                    if not waiters:
                        del self._lock_waiters[key]

        return cancel

    def _wake_lock_waiters(self, key: tuple[str, str]) -> None:
        with self._mutex:
            waiters = self._lock_waiters.pop(key, [])
            self._waiter_count -= len(waiters)
        for wake in waiters:
            wake()

    # -------------------------------------------------------------- watching

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` after every commit (no mutex held, on the writer's thread)."""
        self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[], None]) -> None:
        """Stop calling a listener added by :meth:`add_listener`."""
        try:
            self._listeners.remove(listener)
        except ValueError:
            pass

    def listener_count(self) -> int:
        """Number of registered listeners (watch streams and in-process watchers)."""
        return len(self._listeners)

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

    def _check_id(self, entry_id: str) -> None:
        # Most ids are short printable ASCII: one C-level test settles those (bytes == characters,
        # no control characters) before the full check, which every write would otherwise pay.
        if entry_id.isascii() and entry_id.isprintable() and 0 < len(entry_id) <= self.limits.max_id_bytes:
            return
        if not entry_id:
            raise InvalidArgumentError("entry id is empty: give an id of 1 to 256 bytes (new_id() makes one)")
        size = len(entry_id.encode("utf-8", "surrogatepass"))
        if size > self.limits.max_id_bytes:
            raise InvalidArgumentError(
                f"entry id '{entry_id[:40]}...' is {size} bytes, over the limit of {self.limits.max_id_bytes} "
                "bytes: use a shorter id"
            )
        if _CONTROL.search(entry_id):
            raise InvalidArgumentError(f"entry id {entry_id!r} contains control characters: use printable text")

    def _check_type(self, type_name: str) -> None:
        if type_name in self._good_types:
            return
        if not type_name:
            raise InvalidArgumentError(
                "entry type is empty: the value must be a google.protobuf.Any whose type_url names a message"
            )
        if len(type_name) > self.limits.max_type_bytes or not _TYPE_NAME.match(type_name):
            raise InvalidArgumentError(
                f"entry type {type_name[:80]!r} is not a full protobuf message name such as 'pkg.Message' "
                f"(letters, digits, '_' and '.', at most {self.limits.max_type_bytes} characters)"
            )
        if len(self._good_types) < 10_000:
            self._good_types.add(type_name)


def _check_sa_name(name: str) -> None:
    if not name or not re.fullmatch(r"[A-Za-z0-9_.\-]{1,128}", name):
        raise InvalidArgumentError(
            f"subarchitecture name {name!r} is invalid: use 1 to 128 letters, digits, '_', '-' or '.'"
        )


def _missing(sa: str, entry_id: str) -> str:
    return f"no entry '{entry_id}' in subarchitecture '{sa}'"


def _locked_msg(sa: str, entry_id: str, lock: LockState, action: str) -> str:
    return (
        f"cannot {action} entry '{entry_id}' in subarchitecture '{sa}': it is locked ({lock.mode.name}) by "
        f"component '{lock.holder}'; wait for the unlock (lock() blocks until then) or try again later"
    )
