"""Java and Python components in one system over a real server: reads, writes, watches, permissions, errors.

The scenarios both probes can play are shared with C++ (tests/interop/scenarios_interop.py)."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any

import yaml
from cast_testing_pb2 import Counter, Pose

import cast
from cast.v1 import directory_pb2
from tests.interop import scenarios_interop as s
from tests.interop.java_support import JavaComponent, cast_run, counter_json, java_classpath

# Probes in their own language's commands, and behind the shared driver (for the shared scenarios).
java = s.starter_fixture("java", raw=True)
java_driver = s.starter_fixture("java")


def test_java_writes_python_reads(server: Any, java_driver: s.Start) -> None:
    s.probe_writes_python_reads(server, java_driver, "jwriter")


def test_python_writes_java_reads(server: Any, java_driver: s.Start) -> None:
    assert s.python_writes_probe_reads(server, java_driver, "jreader").quit() == 0


def test_java_gets_named_errors_from_the_real_server(java_driver: s.Start) -> None:
    s.errors_reach_the_probe_by_name(java_driver, "jerr")


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
        first = next(e for e in mine if e["id"] == f"w{n}-0")
        assert int(mine[-2]["version"]) == int(first["version"]) + 1
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


def test_java_unprivileged_cross_sa_write_is_refused(server: Any, java: Any, java_driver: s.Start) -> None:
    s.unprivileged_cross_sa_write_is_refused(server, java_driver, "jlocal")
    # A privileged Java component may write every SA.
    py = server.connect("pylang2", "language")
    try:
        py.add("y", Counter(writer="pylang2", value=1))
    finally:
        py._cast_close()
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
    assert boss.quit() == 0


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


def test_java_component_shows_up_in_the_directory_running_at_once(server: Any, java: Any) -> None:
    """RUNNING is reported when start() returned, not at the next heartbeat (a third of the lease, seconds)."""
    import time

    jc = java("jdir", sa="motor")
    deadline = time.monotonic() + 2
    while True:
        info = server.components()["jdir"]
        if info.state == directory_pb2.COMPONENT_STATE_RUNNING or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert (info.language, info.kind, info.subarchitecture, info.pid) == ("java", "managed", "motor", jc.proc.pid)
    assert info.state == directory_pb2.COMPONENT_STATE_RUNNING
    assert jc.quit() == 0
    assert server.components()["jdir"].state == directory_pb2.COMPONENT_STATE_DISCONNECTED


def test_java_routes_by_sa_across_two_servers(tmp_path: Path) -> None:
    """SAs on two servers: Java reaches each through the directory, and a global watch covers both."""
    config = tmp_path / "two.yaml"
    config.write_text(yaml.safe_dump({
        "system": "two",
        "subarchitectures": {"vision": {}, "motor": {}},
        "servers": {"main": {"subarchitectures": ["vision"]}, "motion": {"subarchitectures": ["motor"]}},
    }))
    java_classpath()  # fails the test if the Java build is missing
    run = cast_run(config, tmp_path / "runtime", tmp_path)
    jc = None
    try:
        state = json.loads((tmp_path / "runtime" / "system.json").read_text())
        assert len({s["endpoint"] for s in state["servers"].values()}) == 2, state
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        env.update(CAST_ENDPOINT=run.endpoint, CAST_COMPONENT_ID="jrouter", CAST_SUBARCHITECTURE="vision",
                   CAST_TOKEN=run.token("jrouter", "vision", privileged=True), CAST_ARGS="{}")
        jc = JavaComponent(env)
        jc.ready()
        watch = jc.ok("watch", filters=[{"kind": "global_type", "type": "cast.testing.Counter"}])["watch"]
        jc.ok("add", id="here", type="cast.testing.Counter", value=counter_json("jrouter", 1))
        jc.ok("add", id="there", type="cast.testing.Counter", value=counter_json("jrouter", 2), sa="motor")
        events = jc.ok("watch_stats", watch=watch, expected=2, timeout_ms=10000)["events"]
        assert sorted((e["sa"], e["id"]) for e in events) == [("motor", "there"), ("vision", "here")]
        # Each revision counts on its own server: both writes are revision 1 of their WM.
        assert [int(e["revision"]) for e in events] == [1, 1]
        py = run.act_as("pyrouter", "motor")
        try:
            assert py.get("there", Counter).value == 2
            assert py.get("here", Counter, subarchitecture="vision").value == 1
        finally:
            py._cast_close()
        # A session on each server: both list the component.
        assert "jrouter" in run.cli("components").stdout
        assert jc.quit() == 0
    finally:
        if jc is not None:
            jc.close()
        run.stop()
