"""A Java managed component's tasks through the task manager, under each policy."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.interop.java_support import JavaComponent


def system(policy: dict[str, Any]) -> dict[str, Any]:
    return {"system": "tasks", "subarchitectures": {"vision": {"task_manager": policy}, "motor": {}}}


@pytest.fixture
def managed(server_factory: Any) -> Iterator[Any]:
    """A Driven Java component (a ManagedComponent) on a server with the given TM policy."""
    started: list[JavaComponent] = []

    def start(policy: dict[str, Any]) -> JavaComponent:
        handle = server_factory(system(policy))
        jc = JavaComponent(handle.env("jtasks", "vision"))
        started.append(jc)
        jc.ready()
        return jc

    yield start
    for jc in started:
        jc.close()


def adopted(jc: JavaComponent, timeout: float = 15.0) -> str:
    ev = jc.wait_event("adopted", timeout)
    assert ev["on_dispatcher"] is True, "hooks run on the dispatcher thread"
    return str(ev["name"])


def test_always_adopts_everything(managed: Any) -> None:
    jc = managed({"policy": "always"})
    ids = {}
    for name in ("a", "b", "c"):
        r = jc.ok("propose", name=name, data_type="cast.testing.Counter", data={"writer": "j", "value": "1"})
        ids[name] = r["task_id"]
    assert sorted(adopted(jc) for _ in range(3)) == ["a", "b", "c"]
    for name in ("a", "b", "c"):
        jc.ok("complete", task_id=ids[name], outcome="SUCCEEDED", reason="done")
    jc.fails("complete", "NotFoundError", task_id="no-such-task")
    assert jc.quit() == 0


def test_fifo_adopts_up_to_max_concurrent_in_order(managed: Any) -> None:
    jc = managed({"policy": "fifo", "max_concurrent": 2})
    ids = {name: jc.ok("propose", name=name)["task_id"] for name in ("a", "b", "c", "d")}
    assert [adopted(jc), adopted(jc)] == ["a", "b"]
    jc.no_event("adopted", within=1.0)
    jc.ok("complete", task_id=ids["a"])
    assert adopted(jc) == "c"
    jc.no_event("adopted", within=0.5)
    jc.ok("retract", task_id=ids["b"])
    assert adopted(jc) == "d"
    jc.ok("complete", task_id=ids["c"], outcome="FAILED", reason="on purpose")
    jc.ok("complete", task_id=ids["d"], outcome="ABANDONED")
    assert jc.quit() == 0


def test_priority_adopts_the_highest_priority_first(managed: Any) -> None:
    jc = managed({"policy": "priority", "max_concurrent": 1})
    blocker = jc.ok("propose", name="blocker")["task_id"]
    assert adopted(jc) == "blocker"
    priorities = (("low", 1), ("high", 5), ("mid", 3))
    ids = {name: jc.ok("propose", name=name, priority=prio)["task_id"] for name, prio in priorities}
    jc.no_event("adopted", within=0.5)
    order = []
    current = blocker
    for _ in range(3):
        jc.ok("complete", task_id=current)
        name = adopted(jc)
        order.append(name)
        current = ids[name]
    assert order == ["high", "mid", "low"]
    jc.ok("complete", task_id=current)
    assert jc.quit() == 0


def test_exclusive_rejects_while_busy(managed: Any) -> None:
    jc = managed({"policy": "exclusive"})
    a = jc.ok("propose", name="a")["task_id"]
    assert adopted(jc) == "a"
    jc.ok("propose", name="b")
    rejected = jc.wait_event("rejected")
    assert rejected["name"] == "b" and "busy" in rejected["reason"], rejected
    jc.ok("complete", task_id=a)
    c = jc.ok("propose", name="c")["task_id"]
    assert adopted(jc) == "c"
    jc.ok("complete", task_id=c)
    assert jc.quit() == 0
