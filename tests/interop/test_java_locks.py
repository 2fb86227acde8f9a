"""Lock contention between a Java and a Python component, in every lock mode, both ways round."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from cast_testing_pb2 import Counter

from cast import DeadlineExceededError, LockedError, LockMode
from tests.interop.java_support import JavaComponent, counter_json

# What the other component may still do while the entry is locked in each mode.
MAY = {
    "O": {"overwrite": False, "delete": True, "read": True},
    "OD": {"overwrite": False, "delete": False, "read": True},
    "ODR": {"overwrite": False, "delete": False, "read": False},
}


@pytest.mark.parametrize("mode", ["O", "OD", "ODR"])
def test_java_holds_python_contends(server: Any, mode: str) -> None:
    jc = JavaComponent(server.env("jlock", "vision"))
    py = server.connect("pylock", "vision")
    try:
        jc.ready()
        for entry_id in ("e", "d"):
            jc.ok("add", id=entry_id, type="cast.testing.Counter", value=counter_json("jlock", 0))
            assert jc.ok("lock", id=entry_id, mode=mode)["depth"] == 1
        assert jc.ok("lock", id="e", mode=mode)["depth"] == 2, "re-entrant"
        may = MAY[mode]
        # Python bumps into the Java lock exactly as the mode says.
        if may["read"]:
            assert py.get("e", Counter).writer == "jlock"
            assert [x.id for x in py.get_all(Counter)] == ["d", "e"]
        else:
            with pytest.raises(LockedError) as exc:
                py.get("e", Counter)
            assert "jlock" in exc.value.message, "the error names the holder"
            assert py.get_all(Counter) == [], "ODR-locked entries of others are left out of type reads"
        assert py.exists("e")
        with pytest.raises(LockedError) as exc:
            py.overwrite("e", Counter(writer="pylock", value=1))
        assert "jlock" in exc.value.message
        assert py.try_lock("e", LockMode[mode]) is False
        assert py.try_lock("e", LockMode.O) is False
        with pytest.raises(DeadlineExceededError):
            py.lock("e", LockMode.O, timeout=0.3)
        if may["delete"]:
            py.delete_entry("d")  # deleting also releases the Java lock on it
            assert not py.exists("d")
        else:
            with pytest.raises(LockedError):
                py.delete_entry("d")
        # Java still writes its own locked entry.
        jc.ok("overwrite", id="e", type="cast.testing.Counter", value=counter_json("jlock", 5))
        # A Python lock waiting for the Java one gets it when Java releases the last level.
        got: list[float] = []

        def wait_for_lock() -> None:
            guard = py.lock("e", LockMode.ODR, timeout=20)
            got.append(time.monotonic())
            guard.unlock()

        waiter = threading.Thread(target=wait_for_lock)
        waiter.start()
        time.sleep(0.3)
        assert jc.ok("unlock", id="e")["depth"] == 1
        time.sleep(0.3)
        assert not got, "one level is still held"
        released = time.monotonic()
        assert jc.ok("unlock", id="e")["depth"] == 0
        waiter.join(20)
        assert got and got[0] >= released
        py.overwrite("e", Counter(writer="pylock", value=9))
        assert jc.quit() == 0
    finally:
        py._cast_close()
        jc.close()


@pytest.mark.parametrize("mode", ["O", "OD", "ODR"])
def test_python_holds_java_contends(server: Any, mode: str) -> None:
    jc = JavaComponent(server.env("jlock2", "vision"))
    py = server.connect("pylock2", "vision")
    try:
        py.add("e", Counter(writer="pylock2", value=0))
        py.add("d", Counter(writer="pylock2", value=0))
        guard = py.lock("e", LockMode[mode])
        py.lock("d", LockMode[mode])
        jc.ready()
        may = MAY[mode]
        if may["read"]:
            assert jc.ok("get", id="e", type="cast.testing.Counter")["value"]["writer"] == "pylock2"
        else:
            err = jc.fails("get", "LockedError", id="e", type="cast.testing.Counter")
            assert "pylock2" in err["message"] and err["code"] == "FAILED_PRECONDITION"
            assert jc.ok("get_all", type="cast.testing.Counter")["entries"] == []
        err = jc.fails("overwrite", "LockedError", id="e", type="cast.testing.Counter", value=counter_json("jlock2", 1))
        assert "pylock2" in err["message"]
        assert jc.ok("try_lock", id="e", mode=mode)["locked"] is False
        assert jc.ok("try_lock", id="e", mode="O")["locked"] is False
        jc.fails("lock", "DeadlineExceededError", id="e", mode="O", timeout_ms=300)
        if may["delete"]:
            jc.ok("delete", id="d")
        else:
            jc.fails("delete", "LockedError", id="d")
        # A blocking Java lock returns once Python unlocks.
        seq = jc.send("lock", id="e", mode=mode, timeout_ms=20000)
        time.sleep(0.5)
        assert seq not in jc.replies, "the Java lock must wait for the Python one"
        guard.unlock()
        r = jc.reply(seq)
        assert r["ok"] and r["depth"] == 1, r
        with pytest.raises(LockedError):
            py.overwrite("e", Counter(writer="pylock2", value=2))
        assert jc.ok("unlock", id="e")["depth"] == 0
        py.overwrite("e", Counter(writer="pylock2", value=3))
        assert jc.quit() == 0
    finally:
        py._cast_close()
        jc.close()
