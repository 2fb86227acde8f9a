"""C++ and Python components in one system over a real server: reads, writes, watches, permissions, errors.

The scenarios both probes can play are shared with Java (tests/interop/scenarios_interop.py)."""

from __future__ import annotations

import threading
from typing import Any

import pytest
from cast_testing_pb2 import Counter, Pose

import cast
from cast.errors import ConsistencyError, NotFoundError
from cast.v1 import directory_pb2
from tests.conftest import wait_for
from tests.interop import scenarios_interop as s
from tests.interop.cpp_support import CppProbe
from tests.interop.probes import counter_json

COUNTER = "cast.testing.Counter"


# Probes in their own language's commands, and behind the shared driver (for the shared scenarios).
cpp = s.starter_fixture("cpp", raw=True)
cpp_driver = s.starter_fixture("cpp")


def test_cpp_writes_python_reads(server: Any, cpp_driver: s.Start) -> None:
    s.probe_writes_python_reads(server, cpp_driver, "cwriter")


def test_python_writes_cpp_reads(server: Any, cpp_driver: s.Start) -> None:
    c = s.python_writes_probe_reads(server, cpp_driver, "creader")
    assert isinstance(c, CppProbe)
    # Only the C++ probe takes a limit on type reads, and reads a Counter as a Pose on request.
    assert [e["id"] for e in CppProbe.ok(c, "getall", COUNTER, "language", 1)["entries"]] == ["b"]
    err = CppProbe.fails(c, "InvalidArgumentError", "get", "Pose", "a", "language")
    assert err["message"] == (
        "entry 'a' in subarchitecture 'language' has type cast.testing.Counter, not cast.testing.Pose: "
        "read it with the right class"
    )
    assert c.quit() == 0


def test_errors_reach_cpp_by_name(cpp_driver: s.Start) -> None:
    s.errors_reach_the_probe_by_name(cpp_driver, "cerr")


def test_unprivileged_cross_sa_write_is_refused(server: Any, cpp_driver: s.Start) -> None:
    s.unprivileged_cross_sa_write_is_refused(server, cpp_driver, "cvision")


def test_privileged_cpp_component_writes_every_sa(server: Any, cpp: Any) -> None:
    c = cpp("cplanner", "vision", privileged=True)
    assert c.ok("whoami")["privileged"] is True
    c.ok("add", COUNTER, "goal", "motor", counter_json("cplanner", 1))
    py = server.connect("pymotor", "motor")
    try:
        entry = py.get_entry("goal", Counter)
        assert entry.author == "cplanner" and entry.value.value == 1
    finally:
        py._cast_close()
    assert c.quit() == 0


def test_cpp_watcher_counts_every_event_of_many_python_writers_once_in_order(server: Any, cpp: Any) -> None:
    writers, per_writer = 6, 60
    c = cpp("cwatcher", "vision")
    c.ok("watch", "all", {"filters": [{"kind": "global", "type": COUNTER, "include_entry": True}]})
    revisions: dict[str, list[int]] = {"vision": [], "language": []}
    lock = threading.Lock()
    failures: list[BaseException] = []

    def write(n: int) -> None:
        sa = "vision" if n % 2 == 0 else "language"
        py = server.connect(f"pw{n}", sa)
        try:
            for i in range(per_writer):
                entry_id = f"w{n}-{i % 10}"
                if i < 10:
                    r = py.add(entry_id, Counter(writer=f"pw{n}", value=i))
                elif i % 3 == 0:
                    r = py.delete_entry(entry_id)
                    r2 = py.add(entry_id, Counter(writer=f"pw{n}", value=i))
                    with lock:
                        revisions[sa].append(r.revision)
                    r = r2
                else:
                    if not py.exists(entry_id):
                        r = py.add(entry_id, Counter(writer=f"pw{n}", value=i))
                    else:
                        r = py.overwrite(entry_id, Counter(writer=f"pw{n}", value=i))
                with lock:
                    revisions[sa].append(r.revision)
        except BaseException as exc:  # reported below, with the thread's context
            failures.append(exc)
        finally:
            py._cast_close()

    threads = [threading.Thread(target=write, args=(n,)) for n in range(writers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not failures, failures
    total = sum(len(v) for v in revisions.values())
    got = c.ok("events", "all", total, 60000, timeout=90)
    assert got["error"] == "" and got["on_dispatcher"] is True
    events = got["events"]
    assert len(events) == total, f"{len(events)} events for {total} writes"
    for sa in ("vision", "language"):
        seen = [e["revision"] for e in events if e["sa"] == sa]
        # Exactly once, in revision order, with no gaps: the revisions the writers got back.
        assert seen == sorted(revisions[sa]), f"{sa}: events out of order or missing"
        assert seen == list(range(1, len(seen) + 1))
    # Per writer, the values arrive in the order they were written.
    for n in range(writers):
        values = [int(e["value"]["value"]) if "value" in e["value"] else 0
                  for e in events if e["source"] == f"pw{n}" and e["operation"] != "DELETE"]
        assert values == sorted(values), f"pw{n}: values out of order"
    assert c.quit() == 0


def test_cpp_filters_select_what_they_say(server: Any, cpp: Any) -> None:
    c = cpp("cfilters", "vision")
    specs = {
        "local": [{"kind": "local", "type": COUNTER}],
        "address": [{"kind": "address", "id": "target", "sa": "language"}],
        "source": [{"kind": "source", "component": "pyb"}],
        "deletes": [{"kind": "operation", "ops": ["DELETE"]}],
        "local_adds": [{"kind": "operation", "ops": ["ADD"], "sa": "local"}],
        "either": [{"kind": "address", "id": "x"}, {"kind": "global", "type": "cast.testing.Pose"}],
    }
    for name, filters in specs.items():
        c.ok("watch", name, {"filters": filters})
    pya = server.connect("pya", "vision")
    pyb = server.connect("pyb", "language")
    try:
        pya.add("x", Counter(writer="pya", value=1))  # local, local_adds, either
        pyb.add("target", Counter(writer="pyb", value=1))  # address, source
        pyb.add("p", Pose(label="p"))  # source, either
        pya.overwrite("x", Counter(writer="pya", value=2))  # local, either
        pyb.delete_entry("target")  # address, source, deletes
        pya.delete_entry("x")  # local, deletes, either
        pya.add("end", Counter(writer="pya", value=0))  # local, local_adds: the last write
    finally:
        pya._cast_close()
        pyb._cast_close()
    # Everything before the last write has been delivered once it has (one stream, in order).
    assert len(c.ok("events", "local", 4, 20000)["events"]) == 4

    def seen(name: str) -> list[tuple[str, str, str]]:
        return [(e["operation"], e["sa"], e["id"]) for e in c.ok("events", name, 0, 0)["events"]]

    assert seen("local") == [("ADD", "vision", "x"), ("OVERWRITE", "vision", "x"), ("DELETE", "vision", "x"),
                             ("ADD", "vision", "end")]
    assert seen("address") == [("ADD", "language", "target"), ("DELETE", "language", "target")]
    assert seen("source") == [("ADD", "language", "target"), ("ADD", "language", "p"),
                              ("DELETE", "language", "target")]
    assert sorted(seen("deletes")) == [("DELETE", "language", "target"), ("DELETE", "vision", "x")]
    assert seen("local_adds") == [("ADD", "vision", "x"), ("ADD", "vision", "end")]
    either = seen("either")
    assert ("ADD", "language", "p") in either and ("OVERWRITE", "vision", "x") in either and len(either) == 4
    assert c.quit() == 0


def test_cancelled_cpp_watch_gets_nothing_more(server: Any, cpp: Any) -> None:
    c = cpp("ccancel", "vision")
    c.ok("watch", "w", {"filters": [{"kind": "local", "type": COUNTER}]})
    c.ok("watch", "control", {"filters": [{"kind": "local", "type": COUNTER}]})
    c.ok("add", COUNTER, "a", "-", counter_json("ccancel", 1))
    assert len(c.ok("events", "w", 1, 10000)["events"]) == 1
    assert c.ok("cancel", "w") == {"active": False}
    c.ok("add", COUNTER, "b", "-", counter_json("ccancel", 2))
    assert len(c.ok("events", "control", 2, 10000)["events"]) == 2  # delivered to the other watch
    assert len(c.ok("events", "w", 0, 0)["events"]) == 1
    assert c.quit() == 0


def test_writes_and_reads_are_copies_across_languages(server: Any, cpp: Any) -> None:
    # Python changes its object after writing; C++ reads what was written, not the change.
    py = server.connect("pycopy", "vision")
    try:
        value = Counter(writer="pycopy", value=1)
        v0 = py.add("v", value).version
        value.value = 99
        assert c_value(cpp("ccopy", "vision"), "v") == 1
        # C++ overwrites; Python's earlier read object does not change.
        earlier = py.get("v", Counter)
        probe = cpp("ccopy2", "vision")
        probe.ok("overwrite", COUNTER, "v", "-", v0, counter_json("ccopy2", 2))
        assert earlier.value == 1
        assert py.get("v", Counter).value == 2
        with pytest.raises(ConsistencyError):
            py.overwrite("v", Counter(writer="pycopy", value=3), expected_version=v0)
        probe.ok("delete", "v", "-", v0 + 1)
        with pytest.raises(NotFoundError):
            py.get("v", Counter)
    finally:
        py._cast_close()


def c_value(probe: CppProbe, entry_id: str) -> int:
    return int(probe.ok("get", COUNTER, entry_id, "-")["value"]["value"])


def test_cpp_component_shows_up_in_the_directory(server: Any, cpp: Any) -> None:
    c = cpp("cdir", "motor")

    def state_is(state: int) -> Any:
        info = server.components().get("cdir")
        return info if info is not None and info.state == state else None

    # The state change is reported at once, not at the next heartbeat.
    info = wait_for(lambda: state_is(directory_pb2.COMPONENT_STATE_RUNNING), timeout=2, what="RUNNING")
    assert info.language == "cpp"
    assert info.kind == "managed"  # the probe is a ManagedComponent
    assert info.subarchitecture == "motor"
    assert info.pid == c.proc.pid
    assert c.quit() == 0
    # A clean exit ends the session at once (no lease to wait for).
    wait_for(lambda: state_is(directory_pb2.COMPONENT_STATE_DISCONNECTED), timeout=5, what="DISCONNECTED")


def test_batch_and_new_ids_from_python_are_visible_to_cpp(server: Any, cpp: Any) -> None:
    py = server.connect("pybatch", "vision")
    try:
        ids = [py.new_id() for _ in range(3)]
        py.batch([("add", i, Counter(writer="pybatch", value=n)) for n, i in enumerate(ids)])
    finally:
        py._cast_close()
    c = cpp("cbatch", "vision")
    # proto JSON leaves out zero values
    assert [int(e["value"].get("value", 0)) for e in c.ok("getall", COUNTER, "-", 0)["entries"]] == [2, 1, 0]
    new = {c.ok("newid")["id"] for _ in range(50)}
    assert len(new) == 50 and all(i.startswith("cbatch:") for i in new)
    assert c.quit() == 0


def test_python_reading_a_cpp_entry_with_the_wrong_class_names_its_type(server: Any, cpp: Any) -> None:
    c = cpp("cwrong", "vision")
    c.ok("add", "Pose", "thing", "-", {"label": "not a counter"})
    py = server.connect("pywrong", "vision")
    try:
        with pytest.raises(cast.InvalidArgumentError) as exc:
            py.get("thing", Counter)
        assert "cast.testing.Pose" in exc.value.message
    finally:
        py._cast_close()
    assert c.quit() == 0


def test_cpp_api_is_safe_to_share_between_threads(server: Any, cpp: Any) -> None:
    """Eight C++ threads add, read, overwrite, lock and unlock at once; one watch sees each change once."""
    c = cpp("cstress", "vision")
    result = c.ok("stress", 8, 40, timeout=120)
    assert result == {"errors": 0, "first_error": "", "changes": 8 * 40 * 2, "duplicates": 0}, result
    py = server.connect("pycount", "vision")
    try:
        entries = py.get_all(Counter)
        floor = entries[0].version - 1
        assert len(entries) == 8 * 40 and all(e.version == floor + 1 and e.author == "cstress" for e in entries)
    finally:
        py._cast_close()
    assert c.quit() == 0


def test_cpp_routes_by_sa_across_two_servers(tmp_path: Any) -> None:
    """SAs on two servers: C++ reaches each through the directory, and a global watch covers both."""
    import os

    import yaml

    from tests.interop.cpp_support import cast_run

    config = tmp_path / "two.yaml"
    config.write_text(yaml.safe_dump({
        "system": "two",
        "subarchitectures": {"vision": {}, "motor": {}},
        "servers": {"main": {"subarchitectures": ["vision"]}, "motion": {"subarchitectures": ["motor"]}},
    }))
    run = cast_run(config, tmp_path / "runtime")
    probe = None
    try:
        servers = run.state()["servers"]
        assert len({s["endpoint"] for s in servers.values()}) == 2, servers
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        env.update(CAST_ENDPOINT=run.endpoint, CAST_COMPONENT_ID="crouter", CAST_SUBARCHITECTURE="vision",
                   CAST_TOKEN=run.token("crouter", "vision", privileged=True), CAST_ARGS="{}")
        probe = CppProbe(env)
        probe.ready()
        probe.ok("watch", "both", {"filters": [{"kind": "global", "type": COUNTER}]})
        probe.ok("add", COUNTER, "here", "-", counter_json("crouter", 1))
        probe.ok("add", COUNTER, "there", "motor", counter_json("crouter", 2))  # on the other server
        events = probe.ok("events", "both", 2, 10000)["events"]
        assert sorted((e["sa"], e["id"]) for e in events) == [("motor", "there"), ("vision", "here")]
        # Each revision counts on its own server: both writes are revision 1 of their WM.
        assert [e["revision"] for e in events] == [1, 1]
        py = run.act_as("pyrouter", "motor")
        try:
            assert py.get("there", Counter).value == 2
        finally:
            py._cast_close()
        assert probe.quit() == 0
    finally:
        if probe is not None:
            probe.close()
        run.stop()
