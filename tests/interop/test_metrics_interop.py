"""Metrics count C++ and Java components exactly as Python ones: known traffic from a probe of SA vision into
language's WM (adds, an overwrite, a delete, a refused add), reads, a watch, a lock wait behind a Python
holder, a task proposed, adopted and completed; and the outcomes a probe reports (``report(name, value)``,
refusals included); read back with `cast stats --json` (Inspection.GetMetrics).

The probes: cpp_client/tests/components/cast_probe.cc and java_client/src/test/java/cast/itest/Driven.java,
behind one vocabulary (tests/interop/probes.py)."""

from __future__ import annotations

import json
import os
import subprocess
import time
from typing import Any

import pytest
from cast_testing_pb2 import Counter

from cast import LockMode
from cast.core.reports import MAX_REPORT_NAMES
from tests.conftest import SECRET, VENV_BIN, ServerHandle
from tests.interop.cpp_support import CppProbe
from tests.interop.probes import COUNTER, CppDriver, Driver, counter_json, start

N_ADDS = 4


def _stats(server: ServerHandle) -> dict[str, Any]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    out = subprocess.run([str(VENV_BIN / "cast"), "stats", "--json", "--endpoint", server.endpoint],
                         env={**env, "CAST_SECRET": SECRET}, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    doc: dict[str, Any] = json.loads(out.stdout)
    return doc


def _task(probe: Driver) -> None:
    """Propose a task, wait for its adoption (the SA's policy is always), complete it."""
    if isinstance(probe, CppDriver):
        task_id = probe.call("propose", "look", 0)["result"]["task_id"]
        adopted = probe.call("decisions", 1, 15000, timeout=25)["result"]["decisions"]
        assert [d["state"] for d in adopted] == ["ADOPTED"], adopted
        assert probe.call("complete", task_id, "SUCCEEDED", "seen")["ok"]
    else:
        task_id = probe.ok("propose", name="look")["task_id"]
        assert probe.wait_event("adopted", 15)["task_id"] == task_id  # type: ignore[attr-defined]
        probe.ok("complete", task_id=task_id, outcome="SUCCEEDED", reason="seen")


def _watch_counters(probe: Driver) -> Any:
    """Watch every Counter change, without values (the task manager's entries are not Counters)."""
    if isinstance(probe, CppDriver):
        CppProbe.ok(probe, "watch", "counters", {"filters": [{"kind": "global", "type": COUNTER}]})
        return "counters"
    return probe.ok("watch", filters=[{"kind": "global_type", "type": COUNTER}])["watch"]


def _size(i: int, writer: str) -> int:
    return len(Counter(writer=writer, value=i).SerializeToString())


@pytest.mark.parametrize("lang", ["cpp", "java"])
def test_known_traffic_from_a_cpp_or_java_component_gives_exact_counts(server: ServerHandle, lang: str) -> None:
    me = f"m-{lang}"
    probe = start(lang, server.env(me, "vision", privileged=True))
    holder = server.connect("pyholder", "language")
    try:
        probe.ready()
        watch = _watch_counters(probe)
        for i in range(N_ADDS):
            probe.ok("add", id=f"m{i}", type=COUNTER, value=counter_json(me, i), sa="language")
        probe.ok("overwrite", id="m0", type=COUNTER, value=counter_json(me, 100), sa="language")
        probe.ok("delete", id=f"m{N_ADDS - 1}", sa="language")
        probe.fails("AlreadyExistsError", "add", id="m1", type=COUNTER, value=counter_json(me, 1), sa="language")
        for entry_id in ("m0", "m1"):
            probe.ok("get", id=entry_id, type=COUNTER, sa="language")
        probe.ok("exists", id="m2", sa="language")
        probe.ok("get_all", type=COUNTER, sa="language")  # m0, m1, m2
        assert len(probe.watch_events(watch, N_ADDS + 2, 15000)) == N_ADDS + 2
        # A lock wait: the probe waits for the Python holder's lock.
        guard = holder.lock("m1", LockMode.O)
        token = probe.send("lock", id="m1", mode="O", sa="language", timeout_ms=20000)
        time.sleep(1.0)  # time for the lock call to reach the server and wait; the holder then lets go
        assert probe.pending(token), "the probe's lock must wait while Python holds the entry"
        guard.unlock()
        assert probe.answer(token)["ok"], probe.output()
        probe.ok("unlock", id="m1", sa="language")
        _task(probe)
        counted = _stats(server)
        assert probe.quit() == 0
    finally:
        holder._cast_close()
        probe.close()
    written = sum(_size(i, me) for i in range(N_ADDS)) + _size(100, me)
    read = _size(100, me) + _size(1, me) + (_size(100, me) + _size(1, me) + _size(2, me))
    mine = counted["components"][me]
    assert mine.pop("lock_wait_s") > 0 and mine.pop("task_wait_s") >= 0  # measured, never asserted
    assert mine == {
        "subarchitecture": "vision", "reads": 4, "entries_read": 5, "writes": N_ADDS + 2, "adds": N_ADDS,
        "overwrites": 1, "deletes": 1, "writes_refused": 1, "bytes_in": written,
        # The watch asked for no values: its events carry none.
        "bytes_out": read, "events": N_ADDS + 2, "event_bytes": 0, "locks": 1, "lock_waits": 1,
        "tasks_proposed": 1, "tasks_adopted": 1, "tasks_rejected": 0, "tasks_retracted": 0, "tasks_completed": 1,
    }, counted["components"]
    cells = {(c["from_sa"], c["to_sa"]): c for c in counted["traffic"]}
    assert cells[("vision", "language")] == {"from_sa": "vision", "to_sa": "language", "reads": 4,
                                             "writes": N_ADDS + 2, "bytes_in": written, "bytes_out": read,
                                             "events": N_ADDS + 2}
    language = counted["subarchitectures"]["language"]
    assert (language["writes"], language["reads"], language["locks"], language["lock_waits"]) == (N_ADDS + 2, 4, 2, 1)
    assert counted["subarchitectures"]["vision"]["tasks_completed"] == 1
    assert counted["delivery_latency"]["watchers"][me]["count"] == N_ADDS + 2


@pytest.mark.parametrize("lang", ["cpp", "java"])
def test_outcomes_a_cpp_or_java_component_reports_are_kept_exactly(server: ServerHandle, lang: str) -> None:
    me = f"r-{lang}"
    probe = start(lang, server.env(me, "language"))
    try:
        probe.ready()
        for correct in ("1", "0", "1", "1"):
            probe.ok("report", name="answers_correct", value=correct)
        for seconds in ("0.5", "0.25", "-2.75"):
            probe.ok("report", name="answer_time_s", value=seconds)
        # Refused by the server, with its message, as the client library's named error: nothing recorded.
        for value in ("NaN", "Infinity", "-Infinity"):
            refused = probe.fails("InvalidArgumentError", "report", name="bad", value=value)
            assert "report 'bad': the value must be a finite number" in refused["message"], refused
        refused = probe.fails("InvalidArgumentError", "report", name="n" * 129, value="1")
        assert "a report name must be 1 to 128 bytes" in refused["message"], refused
        for i in range(MAX_REPORT_NAMES - 2):  # two names are taken already
            probe.ok("report", name=f"m{i}", value=str(i))
        refused = probe.fails("ResourceExhaustedError", "report", name="one-too-many", value="1")
        assert f"component '{me}' already reports {MAX_REPORT_NAMES} names, the limit" in refused["message"]
        counted = _stats(server)
        assert probe.quit() == 0
    finally:
        probe.close()
    mine = counted["reports"][me]
    assert len(mine) == MAX_REPORT_NAMES and not {"bad", "one-too-many", "n" * 129} & set(mine)
    assert {name: {k: v for k, v in r.items() if k != "last_time"}
            for name, r in mine.items() if not name.startswith("m")} == {
        "answers_correct": {"count": 4, "sum": 3.0, "min": 0.0, "max": 1.0, "last": 1.0, "mean": 0.75},
        "answer_time_s": {"count": 3, "sum": -2.0, "min": -2.75, "max": 0.5, "last": -2.75, "mean": -2.0 / 3},
    }
    assert mine["m7"] == {**mine["m7"], "count": 1, "sum": 7.0, "last": 7.0}
