"""Locks: each mode against a second component trying to sneak past it; re-entrancy; release paths."""

from __future__ import annotations

import threading

import pytest

from cast.core.host import BatchOp, MemoryHost
from cast.core.records import Identity, Limits, LockMode, Operation
from cast.core.system import System
from cast.errors import LockedError, NoSessionError, NotFoundError, ResourceExhaustedError

HOLDER = Identity("holder", "vision")
SNEAK = Identity("sneak", "vision")
PRIV = Identity("boss", "coordination", privileged=True)


@pytest.fixture
def host() -> MemoryHost:
    h = MemoryHost(["vision", "coordination"])
    h.add(HOLDER, "vision", "x", "t.T", b"original")
    return h


# What another component may do under each mode: (overwrite, delete, read).
ALLOWED = {
    LockMode.O: (False, True, True),
    LockMode.OD: (False, False, True),
    LockMode.ODR: (False, False, False),
}


@pytest.mark.parametrize("mode", list(LockMode))
@pytest.mark.parametrize("intruder", [SNEAK, PRIV], ids=["same-sa", "privileged"])
def test_each_mode_stops_others(host: MemoryHost, mode: LockMode, intruder: Identity) -> None:
    host.try_lock(HOLDER, "vision", "x", mode)
    may_overwrite, may_delete, may_read = ALLOWED[mode]
    assert not may_overwrite
    with pytest.raises(LockedError, match=f"locked \\({mode.name}\\) by component 'holder'"):
        host.overwrite(intruder, "vision", "x", "t.T", b"sneaky")
    with pytest.raises(LockedError):
        host.batch(intruder, [BatchOp(Operation.OVERWRITE, "vision", "x", "t.T", b"sneaky")])
    with pytest.raises(LockedError):
        host.try_lock(intruder, "vision", "x", LockMode.O)
    if may_read:
        assert host.get(intruder, "vision", "x").data == b"original"
        assert [r.id for r in host.get_by_type(intruder, "vision", "t.T")[0]] == ["x"]
    else:
        with pytest.raises(LockedError, match="cannot read"):
            host.get(intruder, "vision", "x")
        assert host.get_by_type(intruder, "vision", "t.T")[0] == []  # left out, not failed
    # the holder itself is not hindered
    assert host.get(HOLDER, "vision", "x").data == b"original"
    assert host.get_by_type(HOLDER, "vision", "t.T")[0][0].id == "x"
    if may_delete:
        host.delete(intruder, "vision", "x")
        assert host.lock_holder("vision", "x") is None  # the lock went with the entry
    else:
        with pytest.raises(LockedError):
            host.delete(intruder, "vision", "x")
        host.overwrite(HOLDER, "vision", "x", "t.T", b"mine")
        assert host.get(HOLDER, "vision", "x").data == b"mine"


def test_reentrant_and_released_by_holder(host: MemoryHost) -> None:
    assert host.try_lock(HOLDER, "vision", "x", LockMode.O) == 1
    assert host.try_lock(HOLDER, "vision", "x", LockMode.ODR) == 2
    assert host.lock_holder("vision", "x") == ("holder", LockMode.ODR, 2)  # stronger mode kept
    assert host.unlock(HOLDER, "vision", "x") == 1
    with pytest.raises(LockedError):
        host.overwrite(SNEAK, "vision", "x", "t.T", b"")
    assert host.unlock(HOLDER, "vision", "x") == 0
    host.overwrite(SNEAK, "vision", "x", "t.T", b"free")


def test_unlock_by_non_holder_is_refused_and_changes_nothing(host: MemoryHost) -> None:
    with pytest.raises(LockedError, match="not locked"):
        host.unlock(SNEAK, "vision", "x")
    host.try_lock(HOLDER, "vision", "x", LockMode.OD)
    with pytest.raises(LockedError, match="locked by 'holder'.*only the holder"):
        host.unlock(SNEAK, "vision", "x")
    assert host.lock_holder("vision", "x") == ("holder", LockMode.OD, 1)
    with pytest.raises(NotFoundError):
        host.unlock(HOLDER, "vision", "missing")


def test_delete_by_holder_releases_and_wakes_waiters(host: MemoryHost) -> None:
    host.try_lock(HOLDER, "vision", "x", LockMode.OD)
    woken = threading.Event()
    host.wait_for_unlock("vision", "x", woken.set)
    host.delete(HOLDER, "vision", "x")
    assert woken.is_set()
    assert host.locks_of("holder") == []
    host.add(SNEAK, "vision", "x", "t.T", b"")
    assert host.try_lock(SNEAK, "vision", "x", LockMode.O) == 1


def test_locks_are_released_when_the_session_ends() -> None:
    system = System("t", ["vision"])
    host = system.host
    host.add(HOLDER, "vision", "x", "t.T", b"")
    host.add(HOLDER, "vision", "y", "t.T", b"")
    session = system.sessions.register(HOLDER, "python", "unmanaged", 1, "h")
    host.try_lock(HOLDER, "vision", "x", LockMode.ODR)
    host.try_lock(HOLDER, "vision", "y", LockMode.O)
    woken = threading.Event()
    host.wait_for_unlock("vision", "x", woken.set)
    assert system.sessions.end(session)
    assert woken.is_set()
    assert host.lock_holder("vision", "x") is None and host.lock_holder("vision", "y") is None
    host.overwrite(SNEAK, "vision", "x", "t.T", b"after")


def test_locks_are_released_when_the_lease_expires() -> None:
    now = [0.0]
    system = System("t", ["vision"], lease_ms=1000)
    system.sessions._clock = lambda: now[0]
    system.host.add(HOLDER, "vision", "x", "t.T", b"")
    system.sessions.register(HOLDER, "python", "unmanaged", 1, "h")
    system.host.try_lock(HOLDER, "vision", "x", LockMode.OD)
    now[0] = 0.5
    assert system.sessions.expire() == []
    now[0] = 1.5
    assert system.sessions.expire() == ["holder"]
    assert system.host.lock_holder("vision", "x") is None


def test_reregistering_after_a_restart_releases_the_old_incarnations_locks() -> None:
    system = System("t", ["vision"])
    system.host.add(HOLDER, "vision", "x", "t.T", b"")
    system.sessions.register(HOLDER, "python", "unmanaged", 1, "h")
    system.host.try_lock(HOLDER, "vision", "x", LockMode.OD)
    system.sessions.register(HOLDER, "python", "unmanaged", 2, "h")
    assert system.host.lock_holder("vision", "x") is None


def test_waiters_limit() -> None:
    host = MemoryHost(["vision"], Limits(max_lock_waiters=1))
    host.add(HOLDER, "vision", "x", "t.T", b"")
    host.try_lock(HOLDER, "vision", "x", LockMode.O)
    cancel = host.wait_for_unlock("vision", "x", lambda: None)
    with pytest.raises(ResourceExhaustedError, match="max_lock_waiters = 1"):
        host.wait_for_unlock("vision", "x", lambda: None)
    cancel()
    host.wait_for_unlock("vision", "x", lambda: None)


def test_lock_of_missing_entry_is_not_found(host: MemoryHost) -> None:
    with pytest.raises(NotFoundError, match="cannot lock"):
        host.try_lock(HOLDER, "vision", "nope", LockMode.O)


def test_a_component_without_a_live_session_may_not_lock() -> None:
    system = System("t", ["vision"])
    system.host.add(HOLDER, "vision", "x", "t.T", b"")
    with pytest.raises(NoSessionError, match="component 'holder' .* has no live session, so it may not lock entry 'x'"):
        system.host.try_lock(HOLDER, "vision", "x", LockMode.O)
    assert system.host.lock_holder("vision", "x") is None
    session = system.sessions.register(HOLDER, "python", "unmanaged", 1, "h")
    assert system.host.try_lock(HOLDER, "vision", "x", LockMode.O) == 1
    system.sessions.end(session)
    assert system.host.lock_holder("vision", "x") is None


def test_a_session_that_ends_while_a_lock_is_taken_leaves_no_lock() -> None:
    system = System("t", ["vision"])
    system.host.add(HOLDER, "vision", "x", "t.T", b"")
    checks = iter([True, False])
    system.host.session_live = lambda component: next(checks)
    with pytest.raises(NoSessionError):
        system.host.try_lock(HOLDER, "vision", "x", LockMode.OD)
    assert system.host.lock_holder("vision", "x") is None and system.host.locks_of("holder") == []
