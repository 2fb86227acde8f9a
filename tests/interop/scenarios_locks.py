"""Lock contention between a C++ or Java component and a Python one, in every lock mode and both
directions, written once; test_cpp_locks.py and test_java_locks.py run it per language."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from cast_testing_pb2 import Counter

from cast import DeadlineExceededError, LockedError, LockMode
from tests.interop.probes import COUNTER, counter_json, start

MODES = ["O", "OD", "ODR"]

# What another component may still do to an entry locked in each mode.
MAY = {
    "O": {"read": True, "delete": True},
    "OD": {"read": True, "delete": False},
    "ODR": {"read": False, "delete": False},
}


def probe_holds_python_contends(lang: str, server: Any, mode: str, holder: str) -> None:
    """The probe locks (re-entrantly); Python bumps into the lock exactly as the mode says, and a
    blocking Python lock is granted once the probe releases the last level."""
    probe = start(lang, server.env(holder, "vision"))
    py = server.connect("pylock", "vision")
    try:
        probe.ready()
        for entry_id in ("e", "d"):
            probe.ok("add", id=entry_id, type=COUNTER, value=counter_json(holder, 0))
            assert probe.ok("lock", id=entry_id, mode=mode)["depth"] == 1
        assert probe.ok("lock", id="e", mode=mode)["depth"] == 2, "re-entrant"
        may = MAY[mode]
        if may["read"]:
            assert py.get("e", Counter).writer == holder
            assert [x.id for x in py.get_all(Counter)] == ["d", "e"]
        else:
            with pytest.raises(LockedError) as exc:
                py.get("e", Counter)
            assert holder in exc.value.message, "the error names the holder"
            assert py.get_all(Counter) == [], "ODR-locked entries of others are left out of type reads"
        assert py.exists("e")
        with pytest.raises(LockedError) as exc:
            py.overwrite("e", Counter(writer="pylock", value=1))
        assert holder in exc.value.message
        assert py.try_lock("e", LockMode[mode]) is False
        assert py.try_lock("e", LockMode.O) is False
        with pytest.raises(DeadlineExceededError):
            py.lock("e", LockMode.O, timeout=0.3)
        if may["delete"]:
            py.delete_entry("d")  # deleting also releases the probe's lock on it
            assert not py.exists("d")
            probe.fails("NotFoundError", "get", id="d", type=COUNTER)
        else:
            with pytest.raises(LockedError):
                py.delete_entry("d")
        # The holder still writes its own locked entry.
        probe.ok("overwrite", id="e", type=COUNTER, value=counter_json(holder, 5))
        # A Python lock waiting for the probe's gets it when the probe releases the last level.
        got: list[float] = []

        def wait_for_lock() -> None:
            guard = py.lock("e", LockMode.ODR, timeout=20)
            got.append(time.monotonic())
            guard.unlock()

        waiter = threading.Thread(target=wait_for_lock)
        waiter.start()
        time.sleep(0.3)
        # C++ drops a guard (RAII unlock), Java unlocks explicitly; one level is left.
        assert probe.release("e") in (1, None)
        time.sleep(0.3)
        assert not got, "one level is still held"
        released = time.monotonic()
        assert probe.ok("unlock", id="e")["depth"] == 0
        waiter.join(20)
        assert got and got[0] >= released
        py.overwrite("e", Counter(writer="pylock", value=9))
        assert probe.quit() == 0
    finally:
        py._cast_close()
        probe.close()


def python_holds_probe_contends(lang: str, server: Any, mode: str, contender: str, blocking_mode: str) -> None:
    """Python locks; the probe bumps into the lock as the mode says, and its blocking lock (in
    ``blocking_mode``) is granted when Python unlocks."""
    holder = f"py{contender}"
    py = server.connect(holder, "vision")
    probe = start(lang, server.env(contender, "vision"))
    try:
        probe.ready()
        py.add("e", Counter(writer=holder, value=1))
        py.add("d", Counter(writer=holder, value=1))
        guard = py.lock("e", LockMode[mode])
        py.lock("d", LockMode[mode])
        may = MAY[mode]
        if may["read"]:
            assert probe.ok("get", id="e", type=COUNTER)["value"] == counter_json(holder, 1)
            assert [x["id"] for x in probe.ok("get_all", type=COUNTER)["entries"]] == ["d", "e"]
        else:
            err = probe.fails("LockedError", "get", id="e", type=COUNTER)
            assert holder in err["message"] and err["code"] == "FAILED_PRECONDITION", err
            assert probe.ok("get_all", type=COUNTER)["entries"] == []
        assert probe.ok("exists", id="e")["exists"] is True
        err = probe.fails("LockedError", "overwrite", id="e", type=COUNTER, value=counter_json(contender, 2))
        assert err["code"] == "FAILED_PRECONDITION" and holder in err["message"], err
        assert probe.ok("try_lock", id="e", mode=mode)["locked"] is False
        assert probe.ok("try_lock", id="e", mode="O")["locked"] is False
        started = time.monotonic()
        probe.fails("DeadlineExceededError", "lock", id="e", mode="O", timeout_ms=300)
        assert 0.25 <= time.monotonic() - started < 5, "a lock timeout is honoured"
        probe.fails("LockedError", "unlock", id="e")  # not the holder
        if may["delete"]:
            probe.ok("delete", id="d")
            assert not py.exists("d")
        else:
            probe.fails("LockedError", "delete", id="d")
            assert py.exists("d")
        # A blocking lock of the probe is granted when Python releases.
        token = probe.send("lock", id="e", mode=blocking_mode, timeout_ms=20000)
        time.sleep(0.5)
        assert probe.pending(token), "the probe's lock must wait while Python holds the entry"
        guard.unlock()
        r = probe.answer(token, 20)
        assert r["ok"] and r["depth"] == 1, r
        with pytest.raises(LockedError):
            py.overwrite("e", Counter(writer=holder, value=2))
        if blocking_mode == "ODR":
            # Now the probe holds ODR: Python may not even read.
            with pytest.raises(LockedError):
                py.get("e", Counter)
        assert probe.release("e") in (0, None)
        assert py.get("e", Counter).value == 1
        py.overwrite("e", Counter(writer=holder, value=3))
        assert probe.quit() == 0
    finally:
        py._cast_close()
        probe.close()
