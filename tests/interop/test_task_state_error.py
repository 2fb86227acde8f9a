"""A task call the task's state does not allow is a TaskStateError in C++ and Java, as in Python.

The server answers FAILED_PRECONDITION and names the precise class in the ``cast-error``
trailer (docs/client-protocol.md, "Errors"); each client library raises that class, a
LockedError, instead of a plain LockedError. Python's equivalent is the rulebook's
``completing_a_waiting_task_is_a_task_state_error_over_any_transport``
(tests/client/test_rulebook.py).
"""

from __future__ import annotations

from typing import Any

from tests.interop.cpp_support import CppProbe
from tests.interop.java_support import JavaComponent

# One task at a time: a second proposal waits behind the first.
ONE_AT_A_TIME = {
    "system": "task-state",
    "subarchitectures": {"vision": {"task_manager": {"policy": "fifo", "max_concurrent": 1}}},
}


def _assert_task_state_error(answer: dict[str, Any]) -> None:
    assert answer["code"] == "FAILED_PRECONDITION", answer
    assert "waiting, not adopted" in answer["message"], answer


def test_cpp_completing_a_waiting_task_is_a_task_state_error(server_factory: Any) -> None:
    handle = server_factory(ONE_AT_A_TIME)
    probe = CppProbe(handle.env("ctasks", "vision"))
    try:
        probe.ready()
        first = probe.ok("propose", "first", 0)["task_id"]
        second = probe.ok("propose", "second", 0)["task_id"]
        adopted = probe.ok("decisions", 1, 15000, timeout=25)["decisions"]
        assert [d["name"] for d in adopted if d["state"] == "ADOPTED"] == ["first"], adopted
        _assert_task_state_error(probe.fails("TaskStateError", "complete", second, "SUCCEEDED", ""))
        probe.ok("complete", first, "SUCCEEDED", "")  # the adopted one completes as before
        assert probe.quit() == 0
    finally:
        probe.close()


def test_java_completing_a_waiting_task_is_a_task_state_error(server_factory: Any) -> None:
    handle = server_factory(ONE_AT_A_TIME)
    jc = JavaComponent(handle.env("jtasks", "vision"))
    try:
        jc.ready()
        first = jc.ok("propose", name="first")["task_id"]
        second = jc.ok("propose", name="second")["task_id"]
        assert jc.wait_event("adopted", 15.0)["name"] == "first"
        _assert_task_state_error(jc.fails("complete", "TaskStateError", task_id=second, outcome="SUCCEEDED"))
        jc.ok("complete", task_id=first)  # the adopted one completes as before
        assert jc.quit() == 0
    finally:
        jc.close()
