"""Lock contention between a C++ and a Python component, in every lock mode and both directions.

The two directions are shared with Java (tests/interop/scenarios_locks.py); locking another SA's
entry is tested here only."""

from __future__ import annotations

from typing import Any

import pytest
from cast_testing_pb2 import Counter

from cast.errors import LockedError
from tests.interop import scenarios_locks as s
from tests.interop.cpp_support import CppProbe

COUNTER = "cast.testing.Counter"


@pytest.mark.parametrize("mode", s.MODES)
def test_cpp_holds_python_contends(server: Any, mode: str) -> None:
    s.probe_holds_python_contends("cpp", server, mode, "clock")


@pytest.mark.parametrize("mode", s.MODES)
def test_python_holds_cpp_contends(server: Any, mode: str) -> None:
    # The C++ blocking lock is always ODR, so that Python is then refused even a read.
    s.python_holds_probe_contends("cpp", server, mode, "ccontender", blocking_mode="ODR")


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
