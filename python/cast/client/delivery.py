"""How a watch's changes reach its callback: delivery policy (queue or latest) and receiver priority.

``queue`` delivers every change in order; ``latest`` keeps, of the changes of
one entry not yet handed to the callback, only the newest (the server does the
same for what is pending on its side), so a slow consumer of fast data - 30 Hz
images - always gets the newest value next and never a backlog. Priorities
order a component's pending callbacks: high before medium before low, in order
within one (so one watch's changes keep their order).
"""

from __future__ import annotations

import threading
from enum import StrEnum

from cast.client.dispatcher import HIGH, LOW, MEDIUM
from cast.client.types import WorkingMemoryChange
from cast.errors import InvalidArgumentError

__all__ = ["Delivery", "LatestSlots", "Priority", "delivery_of", "priority_of"]


class Delivery(StrEnum):
    """What a watch that falls behind receives: every change (QUEUE) or the newest per entry (LATEST)."""

    QUEUE = "queue"
    LATEST = "latest"


class Priority(StrEnum):
    """The order in which a component's pending callbacks run."""

    HIGH = "high"
    MEDIUM = "medium"
    LOW = "low"


_LEVELS = {Priority.HIGH: HIGH, Priority.MEDIUM: MEDIUM, Priority.LOW: LOW}


def delivery_of(value: Delivery | str) -> Delivery:
    """The delivery named by ``value``; INVALID_ARGUMENT naming the accepted values otherwise."""
    try:
        return Delivery(value)
    except ValueError:
        raise InvalidArgumentError(f"delivery must be 'queue' or 'latest', got {value!r}") from None


def priority_of(value: Priority | str) -> int:
    """The dispatcher level of the priority named by ``value``; INVALID_ARGUMENT otherwise."""
    try:
        return _LEVELS[Priority(value)]
    except ValueError:
        raise InvalidArgumentError(f"priority must be 'high', 'medium' or 'low', got {value!r}") from None


class LatestSlots:
    """The one pending change per (watch, entry) of latest-delivery watches, between arrival and callback."""

    def __init__(self) -> None:
        self._slots: dict[tuple[int, str, str], WorkingMemoryChange] = {}
        self._lock = threading.Lock()  # arrivals come on the watch threads, takes on the dispatcher

    def offer(self, key: tuple[int, str, str], change: WorkingMemoryChange) -> bool:
        """Make ``change`` the pending one of ``key``; True if none was pending (queue a delivery for it)."""
        with self._lock:
            older = self._slots.get(key)
            self._slots[key] = change if older is None else change.replacing(older)
            return older is None

    def take(self, key: tuple[int, str, str]) -> WorkingMemoryChange | None:
        """The pending change of ``key`` (None if the watch was cancelled meanwhile), now no longer pending."""
        with self._lock:
            return self._slots.pop(key, None)

    def drop(self, watch_id: int) -> None:
        """Forget what is pending for a cancelled watch."""
        with self._lock:
            for key in [k for k in self._slots if k[0] == watch_id]:
                del self._slots[key]
