"""Lock contention between a C++ and a Python component, in every lock mode and both directions."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from cast_testing_pb2 import Counter

from cast import LockMode
from cast.errors import DeadlineExceededError, LockedError
from tests.interop.cpp_support import CppProbe

COUNTER = "cast.testing.Counter"

# What another component may still do to an entry locked in each mode.
MAY = {
    "O": {"read": True, "delete": True},
    "OD": {"read": True, "delete": False},
    "ODR": {"read": False, "delete": False},
}


def counter_json(writer: str, value: int) -> dict[str, Any]:
    return {"writer": writer, "value": str(value)}


@pytest.mark.parametrize("mode", ["O", "OD", "ODR"])
def test_cpp_holds_python_contends(server: Any, mode: str) -> None:
    c = CppProbe(server.env("clock", "vision"))
    py = server.connect("pylock", "vision")
    try:
        c.ready()
        for entry_id in ("e", "d"):
            c.ok("add", COUNTER, entry_id, "-", counter_json("clock", 0))
            assert c.ok("lock", entry_id, mode, "-", "-")["depth"] == 1
        assert c.ok("lock", "e", mode, "-", "-")["depth"] == 2, "re-entrant"
        may = MAY[mode]
        if may["read"]:
            assert py.get("e", Counter).writer == "clock"
        else:
            with pytest.raises(LockedError) as exc:
                py.get("e", Counter)
            assert "clock" in exc.value.message, "the error names the holder"
            assert py.get_all(Counter) == [], "ODR-locked entries of others are left out of type reads"
        assert py.exists("e")
        with pytest.raises(LockedError) as exc:
            py.overwrite("e", Counter(writer="pylock", value=1))
        assert "clock" in exc.value.message
        assert py.try_lock("e", LockMode[mode]) is False
        assert py.try_lock("e", LockMode.O) is False
        with pytest.raises(DeadlineExceededError):
            py.lock("e", LockMode.O, timeout=0.3)
        if may["delete"]:
            py.delete_entry("d")  # deleting also releases the C++ lock on it
            assert not py.exists("d")
            c.fails("NotFoundError", "get", COUNTER, "d", "-")
        else:
            with pytest.raises(LockedError):
                py.delete_entry("d")
        # The holder still writes its own locked entry.
        c.ok("overwrite", COUNTER, "e", "-", "-", counter_json("clock", 5))
        # A Python lock waiting for the C++ one gets it when C++ releases the last level.
        got: list[float] = []

        def wait_for_lock() -> None:
            guard = py.lock("e", LockMode.ODR, timeout=20)
            got.append(time.monotonic())
            guard.unlock()

        waiter = threading.Thread(target=wait_for_lock)
        waiter.start()
        time.sleep(0.3)
        c.ok("release", "e", "-")  # one guard goes out of scope: RAII unlock of one level
        time.sleep(0.3)
        assert not got, "one level is still held"
        released = time.monotonic()
        assert c.ok("unlock", "e", "-")["depth"] == 0
        waiter.join(20)
        assert got and got[0] >= released
        py.overwrite("e", Counter(writer="pylock", value=9))
        assert c.quit() == 0
    finally:
        py._cast_close()
        c.close()


@pytest.mark.parametrize("mode", ["O", "OD", "ODR"])
def test_python_holds_cpp_contends(server: Any, mode: str) -> None:
    py = server.connect("pyholder", "vision")
    c = CppProbe(server.env("ccontender", "vision"))
    try:
        c.ready()
        py.add("e", Counter(writer="pyholder", value=1))
        py.add("d", Counter(writer="pyholder", value=1))
        guard = py.lock("e", LockMode[mode])
        py.lock("d", LockMode[mode])
        may = MAY[mode]
        if may["read"]:
            assert c.ok("get", COUNTER, "e", "-")["value"] == counter_json("pyholder", 1)
            assert [x["id"] for x in c.ok("getall", COUNTER, "-", 0)["entries"]] == ["d", "e"]
        else:
            err = c.fails("LockedError", "get", COUNTER, "e", "-")
            assert "pyholder" in err["message"], err
            assert c.ok("getall", COUNTER, "-", 0)["entries"] == []
        assert c.ok("exists", "e", "-") == {"exists": True}
        err = c.fails("LockedError", "overwrite", COUNTER, "e", "-", "-", counter_json("ccontender", 2))
        assert err["code"] == "FAILED_PRECONDITION" and "pyholder" in err["message"], err
        assert c.ok("trylock", "e", mode, "-") == {"locked": False}
        assert c.ok("trylock", "e", "O", "-") == {"locked": False}
        started = time.monotonic()
        c.fails("DeadlineExceededError", "lock", "e", "O", "-", 300)
        assert 0.25 <= time.monotonic() - started < 5, "a lock timeout is honoured"
        c.fails("LockedError", "unlock", "e", "-")  # not the holder
        if may["delete"]:
            c.ok("delete", "d", "-", "-")
            assert not py.exists("d")
        else:
            c.fails("LockedError", "delete", "d", "-", "-")
            assert py.exists("d")
        # A blocking C++ lock is granted when Python releases.
        c.send("lock", "e", "ODR", "-", 20000)
        time.sleep(0.3)
        assert c.lines.empty(), "the C++ lock must wait while Python holds the entry"
        guard.unlock()
        assert c.next_json(20)["result"] == {"depth": 1}
        # Now C++ holds ODR: Python may not even read.
        with pytest.raises(LockedError):
            py.get("e", Counter)
        c.ok("release", "e", "-")
        assert py.get("e", Counter).value == 1
        assert c.quit() == 0
    finally:
        py._cast_close()
        c.close()


def test_lock_of_another_sa_and_try_lock_succeeds_when_free(server: Any) -> None:
    c = CppProbe(server.env("cx", "vision"))
    py = server.connect("pyx", "language")
    try:
        c.ready()
        py.add("far", Counter(writer="pyx", value=1))
        # Locks may be taken on any SA's entries (they guard reads and writes alike).
        assert c.ok("trylock", "far", "OD", "language") == {"locked": True}
        with pytest.raises(LockedError):
            py.overwrite("far", Counter(writer="pyx", value=2))
        assert c.ok("unlock", "far", "language") == {"depth": 0}
        py.overwrite("far", Counter(writer="pyx", value=2))
        assert c.quit() == 0
    finally:
        py._cast_close()
        c.close()
