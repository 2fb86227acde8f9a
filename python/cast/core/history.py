"""The bounded ring of change events of one working memory.

Watchers do not get their own queues: each keeps a cursor (the next revision
it needs) into this ring, so a write costs one append however many watch it.
The ring is bounded both in events and in the bytes of the values its events
keep alive; a cursor older than the ring's start gets HistoryExpiredError.
"""

from __future__ import annotations

from cast.core.records import ChangeEvent
from cast.errors import HistoryExpiredError

__all__ = ["History"]


class History:
    """Events of one WM, revisions ``first`` .. ``last``, oldest dropped first."""

    __slots__ = ("_buf", "_bytes", "_first", "_max_bytes", "_max_events", "_start", "subarchitecture")

    def __init__(self, subarchitecture: str, max_events: int, max_bytes: int) -> None:
        self.subarchitecture = subarchitecture
        self._buf: list[ChangeEvent] = []
        self._start = 0  # index in _buf of revision _first
        self._first = 1
        self._max_events = max(1, max_events)
        self._max_bytes = max_bytes
        self._bytes = 0

    @property
    def first(self) -> int:
        """Oldest revision still kept (``last + 1`` when empty)."""
        return self._first

    @property
    def last(self) -> int:
        """Newest revision (0 before any write)."""
        return self._first + len(self._buf) - self._start - 1

    def reset(self, last: int) -> None:
        """Drop everything and continue numbering after ``last`` (used when restoring state)."""
        self._buf.clear()
        self._start = 0
        self._first = last + 1
        self._bytes = 0

    def append(self, event: ChangeEvent) -> None:
        """Append the event of revision ``last + 1``."""
        buf = self._buf
        buf.append(event)
        if event.entry is not None:
            self._bytes += len(event.entry.data)
        # Kept events are buf[_start:]; at least the newest is always kept.
        while len(buf) - self._start > self._max_events or (
            self._bytes > self._max_bytes and len(buf) - self._start > 1
        ):
            self._drop_oldest()
        # Compact only when the dead prefix dominates, so append stays O(1) amortised.
        if self._start > 1024 and self._start * 2 > len(buf):
            del buf[: self._start]
            self._start = 0

    def _drop_oldest(self) -> None:
        old = self._buf[self._start]
        if old.entry is not None:
            self._bytes -= len(old.entry.data)
        self._buf[self._start] = None  # type: ignore[call-overload]  # release the record now
        self._start += 1
        self._first += 1

    def since(self, next_revision: int) -> list[ChangeEvent]:
        """Events with revision >= ``next_revision``; HistoryExpiredError if some are gone."""
        if next_revision < self._first:
            raise HistoryExpiredError(
                f"subarchitecture '{self.subarchitecture}': revision {next_revision} is no longer in the "
                f"history (kept: {self._first}..{self.last}); resynchronise: read the current state, "
                f"then watch from revision {self.last + 1}"
            )
        offset = self._start + (next_revision - self._first)
        if offset >= len(self._buf):
            return []
        return self._buf[offset:]
