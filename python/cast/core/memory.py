"""The state of one working memory: entries, the type index, versions, locks, history.

This module only holds data and keeps its indexes consistent; every check
(permissions, locks, versions, limits) is made by :mod:`cast.core.host`
before it calls :meth:`WorkingMemory.put` or :meth:`WorkingMemory.remove`.

A WM has two states when its server waits for a journal (``always``,
``batch``): the *visible* state (``entries``, the type index,
``last_versions``, ``history``), which holds only durable writes and is all
that reads, watchers and task policies see, and the *latest* state, which is
the visible one plus ``pending``: the writes committed in memory whose
journal transaction has not yet been made durable. Writes are checked
against the latest state (so versions and order stay right while a group
commit is in flight); the host moves a write from ``pending`` to the visible
state once the journal says it is durable. Without such a journal
``pending`` stays empty and both states are one.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple

from cast.core.history import History
from cast.core.records import EntryRecord, LockMode

__all__ = ["LockState", "Pending", "WorkingMemory"]


class Pending(NamedTuple):
    """The latest state of one id while a write of it waits for the journal."""

    record: EntryRecord | None  # None: deleted
    deleted_version: int | None  # the version it had when deleted
    seq: int  # the event that made this the latest state: once it is visible, so is this


@dataclass
class LockState:
    """A lock on one entry: one holder at a time, re-entrant by depth."""

    holder: str
    mode: LockMode
    depth: int = 1


class WorkingMemory:
    """Entries of one subarchitecture, indexed by id and by type (newest first)."""

    __slots__ = ("_by_type", "assigned", "entries", "history", "last_versions", "locks", "name", "pending",
                 "pending_delta", "total_bytes", "usage")

    def __init__(self, name: str, history_events: int, history_bytes: int) -> None:
        self.name = name
        self.entries: dict[str, EntryRecord] = {}
        # Insertion-ordered dicts used as ordered sets: a write moves the id to
        # the end, so reversed() iterates newest first and limit is O(limit).
        self._by_type: dict[str, dict[str, None]] = {}
        # Last version of deleted entries, so a re-add continues the numbering.
        self.last_versions: dict[str, int] = {}
        self.history = History(name, history_events, history_bytes)
        # Locks belong to the latest state: writes are checked against it.
        self.locks: dict[str, LockState] = {}
        self.pending: dict[str, Pending] = {}
        self.pending_delta = 0  # entries added minus deleted by pending writes
        self.assigned = 0  # the newest revision given to a write, visible or pending
        # Of the latest state: the bytes held (limits.max_total_bytes), and per author [entries, bytes].
        self.total_bytes = 0
        self.usage: dict[str, list[int]] = {}

    @property
    def revision(self) -> int:
        """The WM's visible revision (0 before any write)."""
        return self.history.last

    def latest(self, entry_id: str) -> tuple[EntryRecord | None, int | None]:
        """(record, version it had when deleted) of an id in the latest state."""
        pending = self.pending.get(entry_id)
        if pending is not None:
            return pending.record, pending.deleted_version
        record = self.entries.get(entry_id)
        return record, None if record is not None else self.last_versions.get(entry_id)

    def account(self, old: EntryRecord | None, new: EntryRecord | None) -> None:
        """Move the latest state's usage from ``old`` (replaced or deleted) to ``new``."""
        usage = self.usage
        if old is not None:
            self.total_bytes -= old.size
            held = usage[old.author]
            held[0] -= 1
            held[1] -= old.size
            if not held[0]:
                del usage[old.author]
        if new is not None:
            self.total_bytes += new.size
            mine = usage.get(new.author)
            if mine is None:
                usage[new.author] = [1, new.size]
            else:
                mine[0] += 1
                mine[1] += new.size

    def latest_count(self) -> int:
        """Number of entries in the latest state (for the entries limit)."""
        return len(self.entries) + self.pending_delta

    def put(self, record: EntryRecord) -> EntryRecord | None:
        """Store ``record`` (add or overwrite); return the record it replaced."""
        old = self.entries.get(record.id)
        if old is not None:
            self._unindex(old)
        self.entries[record.id] = record
        self._by_type.setdefault(record.type, {})[record.id] = None
        self.last_versions.pop(record.id, None)
        return old

    def remove(self, entry_id: str) -> EntryRecord:
        """Delete an entry (which must exist), remembering its version.

        Its lock is the host's to drop: locks follow the latest state, which a
        delete reaches before it is visible.
        """
        old = self.entries.pop(entry_id)
        self._unindex(old)
        self.last_versions[entry_id] = old.version
        return old

    def _unindex(self, record: EntryRecord) -> None:
        ids = self._by_type[record.type]
        del ids[record.id]
        if not ids:
            del self._by_type[record.type]

    def newest_of_type(self, type_name: str, limit: int = 0) -> Iterator[EntryRecord]:
        """Entries of ``type_name``, most recently written first, at most ``limit`` (0: all)."""
        ids = self._by_type.get(type_name)
        if not ids:
            return iter(())
        # No generator expression: the compiled build makes one a list, which read every entry of the type
        # for a limit of 1 (docs/decisions.md, "The compiled build").
        newest: Iterator[str] = reversed(ids)
        if limit > 0:
            newest = itertools.islice(newest, limit)
        return map(self.entries.__getitem__, newest)

    def type_counts(self) -> dict[str, int]:
        """Number of entries per type."""
        return {t: len(ids) for t, ids in self._by_type.items()}
