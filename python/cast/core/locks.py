"""Locks on entries: taking, re-entering, releasing, waiting; the lock half of :class:`MemoryHost`.

A lock belongs to the latest state of its WM (the one writes are checked
against, :mod:`cast.core.memory`), has one holder at a time, is re-entrant
by depth, and ends with its holder's session, its release, or the entry's
delete. Only a component with a live session may take one: the session's end
is what releases it. Waiting never happens under the host's mutex: a waiter
registers a callback, is woken by the release, and tries again.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from cast.core.checks import check_id, locked_message, missing_message
from cast.core.memory import LockState, WorkingMemory
from cast.core.records import SYSTEM_TYPES, Identity, Limits, LockMode, no_session, system_entry
from cast.errors import LockedError, NoSessionError, NotFoundError, PermissionDeniedError, ResourceExhaustedError

__all__ = ["Locking"]


class Locking:
    """The lock calls of the host; it shares the host's mutex and working memories."""

    limits: Limits
    _mutex: threading.Lock
    _wms: dict[str, WorkingMemory]

    def _wm(self, sa: str) -> WorkingMemory:
        raise NotImplementedError  # the host's (cast.core.host.MemoryHost._wm)

    def _init_locks(self) -> None:
        self._lock_waiters: dict[tuple[str, str], list[Callable[[], None]]] = {}
        self._waiter_count = 0
        self._held: dict[str, set[tuple[str, str]]] = {}  # component -> locked addresses
        # Whether a component has a live session (cast.core.sessions); None: no sessions (bare core).
        self.session_live: Callable[[str], bool] | None = None

    def try_lock(self, who: Identity, sa: str, entry_id: str, mode: LockMode) -> int:
        """Take (or re-enter) a lock at once; return the depth. FAILED_PRECONDITION if held by another.

        Re-entering keeps the stronger of the held and requested modes. Locks
        are taken on the latest state (the one writes are checked against).
        """
        check_id(entry_id, self.limits)
        mode = LockMode(mode)
        live = self.session_live
        if live is not None and not live(who.component_id):
            raise NoSessionError(no_session(who, f"lock entry '{entry_id}' in subarchitecture '{sa}'"))
        depth = self._take_lock(who, sa, entry_id, mode)
        if live is not None and not live(who.component_id):
            # The session ended while the lock was being taken, after it released what it held.
            self.release_component(who.component_id)
            raise NoSessionError(no_session(who, f"lock entry '{entry_id}' in subarchitecture '{sa}'"))
        return depth

    def _take_lock(self, who: Identity, sa: str, entry_id: str, mode: LockMode) -> int:
        with self._mutex:
            wm = self._wm(sa)
            current = wm.latest(entry_id)[0]
            if current is None:
                raise NotFoundError(missing_message(sa, entry_id) + ": cannot lock it")
            if current.type in SYSTEM_TYPES:
                raise PermissionDeniedError(system_entry(who, sa, entry_id, current.type, "lock"))
            lock = wm.locks.get(entry_id)
            if lock is None:
                wm.locks[entry_id] = LockState(who.component_id, mode)
                self._held.setdefault(who.component_id, set()).add((sa, entry_id))
                return 1
            if lock.holder != who.component_id:
                raise LockedError(locked_message(sa, entry_id, lock, "lock"))
            lock.depth += 1
            lock.mode = max(lock.mode, mode)
            return lock.depth

    def unlock(self, who: Identity, sa: str, entry_id: str) -> int:
        """Release one level of the caller's lock; return the remaining depth."""
        check_id(entry_id, self.limits)
        with self._mutex:
            wm = self._wm(sa)
            if wm.latest(entry_id)[0] is None:
                raise NotFoundError(missing_message(sa, entry_id) + ": cannot unlock it")
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
