"""Checking one write against the latest state of its WM: the rules every write obeys.

:class:`WritePlanner` decides, under the host's mutex, whether a write may be
made and what it makes (the new record and its version); it changes nothing.
The host then commits what it planned. Checks run in this order, so that the
most useful error wins: arguments (INVALID_ARGUMENT), subarchitecture
(NOT_FOUND), permission (PERMISSION_DENIED), existence (NOT_FOUND /
ALREADY_EXISTS), lock (FAILED_PRECONDITION), version (ABORTED), limits
(RESOURCE_EXHAUSTED), value schema (INVALID_ARGUMENT).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from cast.core.checks import TypeChecker, check_id, locked_message, missing_message
from cast.core.memory import LockState, WorkingMemory
from cast.core.records import SYSTEM_TYPES, BatchOp, EntryRecord, Identity, Limits, LockMode, Operation, system_entry
from cast.core.room import Room, Tally
from cast.core.versions import check_outran, next_version
from cast.errors import (
    AlreadyExistsError,
    ConsistencyError,
    InvalidArgumentError,
    LockedError,
    NotFoundError,
    PermissionDeniedError,
    ResourceExhaustedError,
)

__all__ = ["Overlay", "Planned", "ValueValidator", "WritePlanner"]

ValueValidator = Callable[[str, bytes | memoryview], None]
"""Called with (type, bytes) before a write; raises InvalidArgumentError if the bytes do not parse."""


class Planned:
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


class Slot(NamedTuple):
    """State of one address after the earlier operations of a batch."""

    record: EntryRecord | None  # None: deleted in this batch
    deleted_version: int | None  # version it had when deleted


Overlay = dict[tuple[str, str], Slot]
"""The state a batch's earlier operations leave behind, by (SA, id)."""


class WritePlanner:
    """The checks of a write, and the record it makes; holds no state of its own but the type cache."""

    def __init__(
        self,
        limits: Limits,
        validator: ValueValidator | None,
        clock: Callable[[], int],
        version_floor: int,
        room: Room,
    ) -> None:
        self.limits = limits
        self.room = room
        self._validator = validator
        self._clock = clock
        # The lowest version any write of this run may give (cast.core.versions).
        self.version_floor = version_floor
        self._types = TypeChecker(limits)

    def check_type(self, type_name: str) -> None:
        """INVALID_ARGUMENT unless ``type_name`` is a full protobuf message name."""
        self._types.check(type_name)

    def check_args(self, op: BatchOp) -> None:
        """Checks that need no state: id, type, value size, expected version."""
        check_id(op.id, self.limits)
        if op.operation is not Operation.DELETE:
            self._types.check(op.type)
            if len(op.data) > self.limits.max_value_bytes:
                raise InvalidArgumentError(
                    f"value of entry '{op.id}' is {len(op.data)} bytes, over the limit of "
                    f"{self.limits.max_value_bytes} bytes (limits.max_value_bytes): store large data "
                    "elsewhere and keep a reference, or raise the limit in the configuration"
                )
        if op.expected_version is not None and op.expected_version < 0:
            raise InvalidArgumentError(f"expected_version must be >= 0, got {op.expected_version}")

    def plan(
        self,
        wm: WorkingMemory,
        who: Identity,
        op: BatchOp,
        overlay: Overlay | None,
        tally: Tally | None,
        now: int = 0,
        system: bool = False,
    ) -> Planned:
        """Check ``op`` against the latest state of ``wm`` (after ``overlay``); the write it makes.

        ``tally`` tracks what a batch's earlier operations add; ``system``: a
        write by the server itself, which alone writes system entries.
        """
        sa, entry_id = op.subarchitecture, op.id
        if sa != who.subarchitecture and not who.privileged:
            raise PermissionDeniedError(
                f"{who.describe()} may not {op.operation.name.lower()} in subarchitecture '{sa}': "
                "only privileged components write outside their own SA (set privileged: true in the "
                "configuration if this component coordinates other SAs)"
            )
        key = (sa, entry_id)
        slot = overlay.get(key) if overlay is not None else None
        if slot is not None:
            current, deleted_version = slot.record, slot.deleted_version
        elif wm.pending:
            current, deleted_version = wm.latest(entry_id)
        else:  # nothing waits for the journal: the latest state is the visible one (the common case)
            current = wm.entries.get(entry_id)
            deleted_version = None if current is not None else wm.last_versions.get(entry_id)
        if not system and (
            (op.operation is not Operation.DELETE and op.type in SYSTEM_TYPES)
            or (current is not None and current.type in SYSTEM_TYPES)
        ):
            owned = op.type if op.type in SYSTEM_TYPES else current.type  # type: ignore[union-attr]
            raise PermissionDeniedError(system_entry(who, sa, entry_id, owned, op.operation.name.lower()))
        lock = wm.locks.get(entry_id)
        if slot is not None and slot.record is None:
            lock = None  # deleted earlier in this batch: its lock went with it
        now = now or self._clock()
        if op.operation is Operation.ADD:
            planned = self._plan_add(wm, who, op, current, deleted_version, tally, now)
        else:
            planned = self._plan_change(wm, who, op, current, lock, tally, now)
        room = self.room
        grows = (planned.record.size if planned.record is not None else 0) - (current.size if current else 0)
        if tally is not None or room.quotas or wm.total_bytes + grows > room.limits.max_total_bytes:
            room.check(wm, who, planned.old, planned.record, tally)  # else surely room: skip the call
        if overlay is not None:
            deleted = current.version if planned.record is None and current is not None else None
            overlay[key] = Slot(planned.record, deleted)
        return planned

    def _plan_add(
        self, wm: WorkingMemory, who: Identity, op: BatchOp, current: EntryRecord | None,
        deleted_version: int | None, tally: Tally | None, now: int,
    ) -> Planned:
        sa, entry_id = op.subarchitecture, op.id
        if current is not None:
            raise AlreadyExistsError(
                f"entry '{entry_id}' already exists in subarchitecture '{sa}' (version {current.version}, "
                f"type {current.type}): use overwrite to change it, "
                "or a fresh id from new_id() (newId() in C++ and Java)"
            )
        delta = tally.entries.get(sa, 0) if tally is not None else 0
        if wm.latest_count() + delta >= self.limits.max_entries:
            raise ResourceExhaustedError(
                f"subarchitecture '{sa}' holds {wm.latest_count() + delta} entries, the limit "
                f"(limits.max_entries = {self.limits.max_entries}): delete entries or raise the limit"
            )
        if self._validator is not None:
            self._validator(op.type, op.data)
        version = next_version(deleted_version, self.version_floor)
        if version * 1000 > now:  # only a floored version can be near the clock (cast.core.versions)
            check_outran(version, self.version_floor, now, sa, entry_id)
        if tally is not None:
            tally.entries[sa] = delta + 1
        record = EntryRecord(sa, entry_id, op.type, op.data, version, who.component_id, now, 0, op.placed)
        return Planned(wm, Operation.ADD, record, None, who)

    def _plan_change(
        self, wm: WorkingMemory, who: Identity, op: BatchOp, current: EntryRecord | None, lock: LockState | None,
        tally: Tally | None, now: int,
    ) -> Planned:
        """An overwrite or a delete: the entry must exist, no other's lock stop it, the version match."""
        # The operation's name only in the errors: an enum's .name is Python code (enum's property) on every write.
        sa, entry_id = op.subarchitecture, op.id
        if current is None:
            raise NotFoundError(missing_message(sa, entry_id) + f": cannot {op.operation.name.lower()} it")
        if lock is not None and lock.holder != who.component_id:
            if op.operation is Operation.OVERWRITE or lock.mode is not LockMode.O:
                raise LockedError(locked_message(sa, entry_id, lock, op.operation.name.lower()))
        if op.expected_version is not None and op.expected_version != current.version:
            raise ConsistencyError(
                f"entry '{entry_id}' in subarchitecture '{sa}' is at version {current.version}, "
                f"expected {op.expected_version}: it was changed by '{current.author}'; read it again "
                "and retry"
            )
        if op.operation is Operation.DELETE:
            if tally is not None:
                tally.entries[sa] = tally.entries.get(sa, 0) - 1
            return Planned(wm, Operation.DELETE, None, current, who)
        if self._validator is not None:
            self._validator(op.type, op.data)
        version = current.version + 1
        if version < self.version_floor:
            version = self.version_floor
        if version * 1000 > now:
            check_outran(version, self.version_floor, now, sa, entry_id)
        record = EntryRecord(sa, entry_id, op.type, op.data, version, who.component_id, now, 0, op.placed)
        return Planned(wm, Operation.OVERWRITE, record, current, who)
