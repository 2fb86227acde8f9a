"""Java and Python components in one system over a real server: reads, writes, watches, permissions, errors."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Counter, Pose

import cast
from cast.v1 import directory_pb2, directory_pb2_grpc
from tests.interop.java_support import JavaComponent, counter_json


@pytest.fixture
def java(server: Any) -> Iterator[Any]:
    """Start Driven Java components on ``server``; all are killed at the end."""
    started: list[JavaComponent] = []

    def start(component_id: str, sa: str = "vision", privileged: bool = False) -> JavaComponent:
        jc = JavaComponent(server.env(component_id, sa, privileged))
        started.append(jc)
        info = jc.ready()
        assert info["component"] == component_id and info["subarchitecture"] == sa
        return jc

    yield start
    for jc in started:
        jc.close()


def test_java_writes_python_reads(server: Any, java: Any) -> None:
    jc = java("jwriter")
    for i in range(5):
        r = jc.ok("add", id=f"c{i}", type="cast.testing.Counter", value=counter_json("jwriter", i))
        assert r["version"] == 0
    jc.ok("overwrite", id="c1", type="cast.testing.Counter", value=counter_json("jwriter", 100), expected_version=0)
    jc.fails("overwrite", "ConsistencyError", id="c1", type="cast.testing.Counter",
             value=counter_json("jwriter", 101), expected_version=0)
    jc.ok("delete", id="c4", expected_version=0)
    jc.ok("add", id="p", type="cast.testing.Pose", value={"x": 1.5, "y": -2.0, "label": "gauche", "tags": ["a", "é"]})

    py = server.connect("pyreader", "vision")
    try:
        assert py.get("c0", Counter) == Counter(writer="jwriter", value=0)
        entry = py.get_entry("c1", Counter)
        assert entry.value == Counter(writer="jwriter", value=100)
        assert entry.version == 1
        assert entry.author == "jwriter"
        assert not py.exists("c4")
        assert [e.id for e in py.get_all(Counter)] == ["c1", "c3", "c2", "c0"]  # newest first
        assert py.get("p", Pose) == Pose(x=1.5, y=-2.0, label="gauche", tags=["a", "é"])
    finally:
        py._cast_close()

    # The Java client registered the schemas of what it wrote, so tools can render them.
    with grpc.insecure_channel(server.endpoint) as channel:
        stub = directory_pb2_grpc.DirectoryStub(channel)
        md = (("authorization", f"Bearer {server.token('tool', 'vision')}"),)
        for type_name in ("cast.testing.Counter", "cast.testing.Pose"):
            schema = stub.GetSchema(directory_pb2.GetSchemaRequest(type=type_name), metadata=md)
            assert [f.name for f in schema.files.file] == ["cast_testing.proto"]
    assert jc.quit() == 0


def test_python_writes_java_reads(server: Any, java: Any) -> None:
    py = server.connect("pywriter", "language")
    try:
        py.add("a", Counter(writer="pywriter", value=-(2**63)))
        py.add("b", Counter(writer="pywriter", value=2**63 - 1))
        py.overwrite("b", Counter(writer="pywriter", value=7), expected_version=0)
        py.add("pose", Pose(x=0.25, label="ünïcödé"))
    finally:
        py._cast_close()
    jc = java("jreader", sa="vision")
    r = jc.ok("get", id="a", type="cast.testing.Counter", sa="language")
    assert r["value"] == {"writer": "pywriter", "value": str(-(2**63))}
    assert r["version"] == 0 and r["author"] == "pywriter" and r["type"] == "cast.testing.Counter"
    r = jc.ok("get", id="b", type="cast.testing.Counter", sa="language")
    assert r["value"] == {"writer": "pywriter", "value": "7"} and r["version"] == 1
    assert jc.ok("get", id="pose", type="cast.testing.Pose", sa="language")["value"] == {"x": 0.25, "label": "ünïcödé"}
    entries = jc.ok("get_all", type="cast.testing.Counter", sa="language")["entries"]
    assert [e["id"] for e in entries] == ["b", "a"]
    assert jc.ok("exists", id="a", sa="language")["exists"] is True
    assert jc.ok("exists", id="a")["exists"] is False  # own SA (vision) has no such entry
    wrong = jc.fails("get", "InvalidArgumentError", id="pose", type="cast.testing.Counter", sa="language")
    assert "has type cast.testing.Pose, not cast.testing.Counter" in wrong["message"]
    assert jc.quit() == 0


def test_java_gets_named_errors_from_the_real_server(server: Any, java: Any) -> None:
    jc = java("jerr")
    jc.ok("add", id="x", type="cast.testing.Counter", value=counter_json("jerr", 1))
    assert jc.fails("add", "AlreadyExistsError", id="x", type="cast.testing.Counter",
                    value=counter_json("jerr", 2))["code"] == "ALREADY_EXISTS"
    assert jc.fails("get", "NotFoundError", id="nope", type="cast.testing.Counter")["code"] == "NOT_FOUND"
    jc.fails("overwrite", "NotFoundError", id="nope", type="cast.testing.Counter", value=counter_json("jerr", 2))
    jc.fails("delete", "ConsistencyError", id="x", expected_version=5)
    unknown = jc.fails("get", "NotFoundError", id="x", type="cast.testing.Counter", sa="no-such-sa")
    assert "vision" in unknown["message"], "the server lists the SAs it knows"
    jc.fails("add", "InvalidArgumentError", id="", type="cast.testing.Counter", value=counter_json("jerr", 2))
    jc.fails("unlock", "LockedError", id="x")  # not held
    ids = {jc.ok("new_id")["id"] for _ in range(20)}
    assert len(ids) == 20 and all(i.startswith("jerr:") for i in ids)
    assert jc.quit() == 0


def test_java_watcher_counts_every_event_of_many_python_writers_once_in_order(server: Any, java: Any) -> None:
    jc = java("jwatch")
    counters = {"kind": "global_type", "type": "cast.testing.Counter", "include_entry": True}
    watch = jc.ok("watch", filters=[counters])["watch"]
    # A second watch on the same stream that must see only the deletes.
    deletes = jc.ok("watch", filters=[{"kind": "operation", "operations": ["DELETE"], "sa": "vision"}])["watch"]
    writers, per_writer = 4, 60

    def write(n: int) -> None:
        comp = server.connect(f"pyw{n}", "vision")
        try:
            for i in range(per_writer):
                comp.add(f"w{n}-{i}", Counter(writer=f"pyw{n}", value=i))
            comp.overwrite(f"w{n}-0", Counter(writer=f"pyw{n}", value=per_writer))
            comp.delete_entry(f"w{n}-1")
            comp.add(f"pose{n}", Pose(label="not a counter"))
        finally:
            comp._cast_close()

    threads = [threading.Thread(target=write, args=(n,)) for n in range(writers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    expected = writers * (per_writer + 2)
    stats = jc.ok("watch_stats", watch=watch, expected=expected, timeout_ms=30000)
    events = stats["events"]
    assert len(events) == expected, f"{len(events)} events, expected {expected}"
    revisions = [int(e["revision"]) for e in events]
    assert revisions == sorted(revisions) and len(set(revisions)) == len(revisions), "revision order, each once"
    assert all(e["type"] == "cast.testing.Counter" for e in events)
    for n in range(writers):
        mine = [e for e in events if e["source"] == f"pyw{n}"]
        adds = [int(e["value"].get("value", "0")) for e in mine if e["op"] == "ADD"]
        assert adds == list(range(per_writer)), f"writer {n}: values out of order or missing"
        assert [e["op"] for e in mine][-2:] == ["OVERWRITE", "DELETE"]
        assert mine[-2]["version"] == 1
    assert len(stats["threads"]) == 1 and stats["threads"][0].startswith("cast-dispatch-"), stats["threads"]
    dstats = jc.ok("watch_stats", watch=deletes, expected=writers, timeout_ms=10000)
    assert sorted(e["id"] for e in dstats["events"]) == sorted(f"w{n}-1" for n in range(writers))
    # Nothing more arrives (exactly once), and a cancelled watch gets nothing new.
    jc.ok("cancel", watch=watch)
    py = server.connect("pylate", "vision")
    try:
        py.add("late", Counter(writer="pylate", value=1))
        py.delete_entry("late")
    finally:
        py._cast_close()
    dstats = jc.ok("watch_stats", watch=deletes, expected=writers + 1, timeout_ms=10000)
    assert len(dstats["events"]) == writers + 1
    after = jc.ok("watch_stats", watch=watch)
    assert len(after["events"]) == expected and after["active"] is False
    assert jc.quit() == 0


def test_java_unprivileged_cross_sa_write_is_refused(server: Any, java: Any) -> None:
    jc = java("jlocal", sa="vision")
    err = jc.fails("add", "PermissionDeniedError", id="x", type="cast.testing.Counter",
                   value=counter_json("jlocal", 1), sa="language")
    assert err["code"] == "PERMISSION_DENIED"
    assert "jlocal" in err["message"] and "vision" in err["message"] and "language" in err["message"], err["message"]
    py = server.connect("pylang", "language")
    try:
        assert not py.exists("x")
        py.add("y", Counter(writer="pylang", value=1))
    finally:
        py._cast_close()
    jc.fails("overwrite", "PermissionDeniedError", id="y", type="cast.testing.Counter",
             value=counter_json("jlocal", 2), sa="language")
    jc.fails("delete", "PermissionDeniedError", id="y", sa="language")
    assert jc.ok("get", id="y", type="cast.testing.Counter", sa="language")["value"]["writer"] == "pylang"
    # A privileged Java component may write every SA.
    boss = java("jboss", sa="motor", privileged=True)
    assert boss.ok("whoami")["privileged"] is True
    boss.ok("overwrite", id="y", type="cast.testing.Counter", value=counter_json("jboss", 3), sa="language")
    boss.ok("add", id="z", type="cast.testing.Counter", value=counter_json("jboss", 4), sa="vision")
    py = server.connect("pycheck", "vision")
    try:
        assert py.get("y", Counter, subarchitecture="language") == Counter(writer="jboss", value=3)
        assert py.get_entry("z", Counter).author == "jboss"
    finally:
        py._cast_close()
    assert jc.quit() == 0 and boss.quit() == 0


def test_python_sees_java_changes_through_its_own_watch(server: Any, java: Any) -> None:
    py = server.connect("pywatch", "vision")
    seen: list[cast.WorkingMemoryChange] = []
    done = threading.Event()

    def changed(ch: cast.WorkingMemoryChange) -> None:
        seen.append(ch)
        if len(seen) == 3:
            done.set()

    try:
        py.on_change(cast.source_filter("jsrc"), changed)
        jc = java("jsrc")
        jc.ok("add", id="a", type="cast.testing.Counter", value=counter_json("jsrc", 1))
        jc.ok("overwrite", id="a", type="cast.testing.Counter", value=counter_json("jsrc", 2))
        jc.ok("delete", id="a")
        assert done.wait(10)
        assert [c.operation.name for c in seen] == ["ADD", "OVERWRITE", "DELETE"]
        assert all(c.source_component == "jsrc" and c.source_subarchitecture == "vision" for c in seen)
        assert jc.quit() == 0
    finally:
        py._cast_close()


def test_a_stuck_java_watcher_never_blocks_writers_and_is_told_past_the_history(server_factory: Any) -> None:
    server = server_factory({"system": "lag", "limits": {"history_events": 64}, "subarchitectures": {"vision": {}}})
    env = dict(server.env("jslow", "vision"), DRIVEN_MAX_PENDING="4")
    jc = JavaComponent(env)
    py = server.connect("pyfast", "vision")
    try:
        jc.ready()
        watch = jc.ok("watch", gated=True, filters=[{"kind": "local_type", "type": "cast.testing.Pose",
                                                      "include_entry": True}])["watch"]
        # Far more than the history, in events and in bytes (past the transport's buffers), while the
        # Java callback is stuck: the writer is never held up.
        label = "x" * 2048
        started = time.monotonic()
        for i in range(3000):
            py.add(f"p{i}", Pose(x=i, label=label))
        assert time.monotonic() - started < 60
        jc.ok("open_gate")
        failed = jc.wait_event("watch_failed", timeout=60)
        assert failed["error"] == "HistoryExpiredError", failed
        stats = jc.ok("watch_stats", watch=watch)
        events = stats["events"]
        assert 0 < len(events) < 3000, "some events were delivered, then the watcher was told it fell behind"
        assert [e["id"] for e in events] == [f"p{i}" for i in range(len(events))], "no gap before the failure"
        # Resynchronising: a new watch on a new stream gets the changes from now on.
        again = jc.ok("watch", filters=[{"kind": "local_type", "type": "cast.testing.Pose"}])["watch"]
        py.add("after", Pose(label="after"))
        stats = jc.ok("watch_stats", watch=again, expected=1, timeout_ms=10000)
        assert [e["id"] for e in stats["events"]] == ["after"]
        assert jc.quit() == 0
    finally:
        py._cast_close()
        jc.close()
