"""Lock contention between a Java and a Python component, in every lock mode, both ways round.

The scenarios are shared with C++ (tests/interop/scenarios_locks.py)."""

from __future__ import annotations

from typing import Any

import pytest

from tests.interop import scenarios_locks as s


@pytest.mark.parametrize("mode", s.MODES)
def test_java_holds_python_contends(server: Any, mode: str) -> None:
    s.probe_holds_python_contends("java", server, mode, "jlock")


@pytest.mark.parametrize("mode", s.MODES)
def test_python_holds_java_contends(server: Any, mode: str) -> None:
    # The Java blocking lock is taken in the mode under test.
    s.python_holds_probe_contends("java", server, mode, "jlock2", blocking_mode=mode)
