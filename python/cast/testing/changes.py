"""Collecting change events for a test, and waiting for them with a failure that lists what came."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

from cast.client.component import UnmanagedComponent
from cast.client.types import WorkingMemoryChange
from cast.testing.describe import describe_change
from cast.testing.waiting import DEFAULT_TIMEOUT_S, wait_for

__all__ = ["ChangeCollector"]


class ChangeCollector:
    """The changes a watch of its own delivered, in the order they came (revision order per WM).

    Made by :meth:`cast.testing.LocalSystem.collect_changes`, which registers
    the watch before it returns: every matching change made after that is
    collected. Closed with the system, or by :meth:`close`.
    """

    def __init__(self, watcher: UnmanagedComponent) -> None:
        self._watcher = watcher
        self._changes: list[WorkingMemoryChange] = []
        self._lock = threading.Lock()

    def _collect(self, change: WorkingMemoryChange) -> None:
        with self._lock:
            self._changes.append(change)

    @property
    def changes(self) -> list[WorkingMemoryChange]:
        """The changes collected so far (a copy)."""
        with self._lock:
            return list(self._changes)

    def __len__(self) -> int:
        with self._lock:
            return len(self._changes)

    def __iter__(self) -> Iterator[WorkingMemoryChange]:
        return iter(self.changes)

    def describe(self) -> str:
        """One line per change collected (with its value when the filter asked for the entry)."""
        changes = self.changes
        if not changes:
            return "no changes"
        return f"{len(changes)} change{'s' if len(changes) != 1 else ''}:\n" + "\n".join(
            f"  {describe_change(c)}" for c in changes)

    def wait_for_count(self, count: int, timeout: float = DEFAULT_TIMEOUT_S) -> list[WorkingMemoryChange]:
        """Wait until at least ``count`` changes came; the first ``count``. The failure lists those that came."""
        def enough() -> list[WorkingMemoryChange]:
            changes = self.changes
            assert len(changes) >= count, f"expected {count} change{'s' if count != 1 else ''}, got {self.describe()}"
            return changes[:count]

        return wait_for(enough, timeout, f"{count} change{'s' if count != 1 else ''}")

    def wait_for_change(
        self, predicate: Callable[[WorkingMemoryChange], bool], timeout: float = DEFAULT_TIMEOUT_S, what: str = "",
    ) -> WorkingMemoryChange:
        """Wait for a change that satisfies ``predicate``; the first one. The failure lists those that came."""
        awaited = what or "a matching change"

        def matching() -> WorkingMemoryChange:
            found = next((c for c in self.changes if predicate(c)), None)
            assert found is not None, f"no change matched; got {self.describe()}"
            return found

        return wait_for(matching, timeout, awaited)

    def clear(self) -> None:
        """Forget the changes collected so far (collecting goes on)."""
        with self._lock:
            self._changes.clear()

    def close(self) -> None:
        """Stop collecting (the watch's connection is closed; what was collected stays)."""
        self._watcher.request_stop()
        self._watcher._cast_close()
