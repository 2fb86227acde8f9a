"""The state of one working memory: entries, the type index, versions, locks, history.

This module only holds data and keeps its indexes consistent; every check
(permissions, locks, versions, limits) is made by :mod:`cast.core.host`
before it calls :meth:`WorkingMemory.put` or :meth:`WorkingMemory.remove`.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass

from cast.core.history import History
from cast.core.records import EntryRecord, LockMode

__all__ = ["LockState", "WorkingMemory"]


@dataclass
class LockState:
    """A lock on one entry: one holder at a time, re-entrant by depth."""

    holder: str
    mode: LockMode
    depth: int = 1


class WorkingMemory:
    """Entries of one subarchitecture, indexed by id and by type (newest first)."""

    __slots__ = ("_by_type", "entries", "history", "last_versions", "locks", "name")

    def __init__(self, name: str, history_events: int, history_bytes: int) -> None:
        self.name = name
        self.entries: dict[str, EntryRecord] = {}
        # Insertion-ordered dicts used as ordered sets: a write moves the id to
        # the end, so reversed() iterates newest first and limit is O(limit).
        self._by_type: dict[str, dict[str, None]] = {}
        # Last version of deleted entries, so a re-add continues the numbering.
        self.last_versions: dict[str, int] = {}
        self.history = History(name, history_events, history_bytes)
        self.locks: dict[str, LockState] = {}

    @property
    def revision(self) -> int:
        """The WM's current revision (0 before any write)."""
        return self.history.last

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
        """Delete an entry (which must exist), remembering its version; drop its lock."""
        old = self.entries.pop(entry_id)
        self._unindex(old)
        self.last_versions[entry_id] = old.version
        self.locks.pop(entry_id, None)
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
        it = (self.entries[i] for i in reversed(ids))
        return itertools.islice(it, limit) if limit > 0 else it

    def type_counts(self) -> dict[str, int]:
        """Number of entries per type."""
        return {t: len(ids) for t, ids in self._by_type.items()}
