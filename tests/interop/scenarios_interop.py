"""C++ or Java and Python components in one system over a real server, written once: writes read
across languages, named errors, refused cross-SA writes. test_cpp_interop.py and test_java_interop.py
run them per language, next to the scenarios only one probe can play."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Counter, Pose

from cast.v1 import directory_pb2, directory_pb2_grpc
from tests.interop.cpp_support import CppProbe
from tests.interop.java_support import JavaComponent
from tests.interop.probes import COUNTER, DRIVERS, Driver, counter_json

POSE = "cast.testing.Pose"
RAW: dict[str, type[CppProbe] | type[JavaComponent]] = {"cpp": CppProbe, "java": JavaComponent}

# Starts a ready probe: (component id, SA, privileged) -> driver.
Start = Callable[..., Driver]


def probe_starter(server: Any, lang: str, raw: bool = False) -> Iterator[Any]:
    """The body of a per-language fixture: start ready probes on ``server``; all are killed at the end.

    With ``raw`` the probes speak their own language's commands (CppProbe, JavaComponent), for the
    scenarios only that probe can play; else the shared driver vocabulary (probes.Driver).
    """
    cls = RAW[lang] if raw else DRIVERS[lang]
    started: list[Any] = []

    def start_ready(component_id: str, sa: str = "vision", privileged: bool = False) -> Any:
        probe = cls(server.env(component_id, sa, privileged))
        started.append(probe)
        # The C++ ready line says "id", Java's ready event "component" and "subarchitecture".
        info = probe.ready()
        assert info.get("id", info.get("component")) == component_id, info
        assert info.get("subarchitecture", sa) == sa, info
        return probe

    yield start_ready
    for probe in started:
        probe.close()


def starter_fixture(lang: str, raw: bool = False) -> Any:
    """A pytest fixture (on ``server``) that starts ready probes of ``lang``; see probe_starter."""

    @pytest.fixture
    def fixture(server: Any) -> Iterator[Any]:
        yield from probe_starter(server, lang, raw)

    return fixture


def probe_writes_python_reads(server: Any, start_ready: Start, writer: str) -> None:
    """Adds, a checked overwrite, a delete and a Pose written by the probe read back in Python."""
    c = start_ready(writer)
    # A memory-only server starts versions at its epoch floor (microseconds, past 2**50): the
    # probe carries them as 64-bit numbers both ways.
    v0 = c.ok("add", id="c0", type=COUNTER, value=counter_json(writer, 0))["version"]
    assert v0 > 2**50
    for i in range(1, 5):
        assert c.ok("add", id=f"c{i}", type=COUNTER, value=counter_json(writer, i))["version"] == v0
    assert c.ok("overwrite", id="c1", type=COUNTER, value=counter_json(writer, 100),
                expected_version=v0)["version"] == v0 + 1
    c.fails("ConsistencyError", "overwrite", id="c1", type=COUNTER, value=counter_json(writer, 101),
            expected_version=v0)
    c.ok("delete", id="c4", expected_version=v0)
    c.ok("add", id="p", type=POSE, value={"x": 1.5, "y": -2.0, "label": "gauche ü", "tags": ["a", "é"]})

    py = server.connect("pyreader", "vision")
    try:
        assert py.get("c0", Counter) == Counter(writer=writer, value=0)
        entry = py.get_entry("c1", Counter)
        assert entry.value == Counter(writer=writer, value=100)
        assert entry.version == v0 + 1
        assert entry.author == writer
        assert not py.exists("c4")
        assert [e.id for e in py.get_all(Counter)] == ["c1", "c3", "c2", "c0"]  # newest first
        assert py.get("p", Pose) == Pose(x=1.5, y=-2.0, label="gauche ü", tags=["a", "é"])
    finally:
        py._cast_close()

    # The client registered the schemas of what it wrote, so tools render them as JSON.
    with grpc.insecure_channel(server.endpoint) as channel:
        stub = directory_pb2_grpc.DirectoryStub(channel)
        md = (("authorization", f"Bearer {server.token('tool', 'vision')}"),)
        for type_name in (COUNTER, POSE):
            schema = stub.GetSchema(directory_pb2.GetSchemaRequest(type=type_name), metadata=md)
            assert [f.name for f in schema.files.file] == ["cast_testing.proto"]
    assert c.quit() == 0


def python_writes_probe_reads(server: Any, start_ready: Start, reader: str) -> Driver:
    """Python's extreme int64 values, a checked overwrite and unicode read by the probe in another SA.

    Returns the probe, still running, for the checks only one language can make; the caller quits it.
    """
    py = server.connect("pywriter", "language")
    try:
        a = py.add("a", Counter(writer="pywriter", value=-(2**63))).version
        b = py.add("b", Counter(writer="pywriter", value=2**63 - 1)).version
        py.overwrite("b", Counter(writer="pywriter", value=7), expected_version=b)
        py.add("pose", Pose(x=0.25, label="ünïcödé", tags=["x"]))
    finally:
        py._cast_close()
    c = start_ready(reader, "vision")
    r = c.ok("get", id="a", type=COUNTER, sa="language")
    assert r["value"] == counter_json("pywriter", -(2**63))
    assert r["version"] == a and r["author"] == "pywriter" and r["type"] == COUNTER
    r = c.ok("get", id="b", type=COUNTER, sa="language")
    assert r["value"] == counter_json("pywriter", 7) and r["version"] == b + 1
    assert c.ok("get", id="pose", type=POSE, sa="language")["value"] == {"x": 0.25, "label": "ünïcödé", "tags": ["x"]}
    assert [e["id"] for e in c.ok("get_all", type=COUNTER, sa="language")["entries"]] == ["b", "a"]
    assert c.ok("exists", id="a", sa="language")["exists"] is True
    assert c.ok("exists", id="a")["exists"] is False  # the own SA (vision) has no such entry
    # The reader decodes with the class it asks for, and says so when it is the wrong one.
    wrong = c.fails("InvalidArgumentError", "get", id="pose", type=COUNTER, sa="language")
    assert "has type cast.testing.Pose, not cast.testing.Counter" in wrong["message"], wrong
    return c


def errors_reach_the_probe_by_name(start_ready: Start, component: str) -> None:
    """Each server error reaches the probe as the named error with its status code; new ids are unique."""
    c = start_ready(component)
    c.ok("add", id="x", type=COUNTER, value=counter_json(component, 1))
    dup = c.fails("AlreadyExistsError", "add", id="x", type=COUNTER, value=counter_json(component, 2))
    assert dup["code"] == "ALREADY_EXISTS" and "already exists" in dup["message"], dup
    assert c.fails("NotFoundError", "get", id="nope", type=COUNTER)["code"] == "NOT_FOUND"
    assert c.fails("NotFoundError", "overwrite", id="nope", type=COUNTER,
                   value=counter_json(component, 2))["code"] == "NOT_FOUND"
    assert c.fails("ConsistencyError", "delete", id="x", expected_version=3)["code"] == "ABORTED"
    missing_sa = c.fails("NotFoundError", "get", id="x", type=COUNTER, sa="atlantis")
    # The server names the SA it does not know, and lists those it does.
    assert "atlantis" in missing_sa["message"] and "vision" in missing_sa["message"], missing_sa
    c.fails("InvalidArgumentError", "add", id="", type=COUNTER, value=counter_json(component, 2))  # ids: 1-256 bytes
    c.fails("LockedError", "unlock", id="x")  # not held
    ids = {c.ok("new_id")["id"] for _ in range(20)}
    assert len(ids) == 20 and all(i.startswith(f"{component}:") for i in ids)
    assert c.quit() == 0


def unprivileged_cross_sa_write_is_refused(server: Any, start_ready: Start, component: str) -> None:
    """Writes into another SA are refused with a message naming who, where from and where to; reads are open."""
    c = start_ready(component, "vision")
    err = c.fails("PermissionDeniedError", "add", id="goal", type=COUNTER, value=counter_json(component, 1),
                  sa="language")
    assert err["code"] == "PERMISSION_DENIED"
    for word in (component, "vision", "language"):
        assert word in err["message"], err
    py = server.connect("pylang", "language")
    try:
        assert not py.exists("goal")
        py.add("goal", Counter(writer="pylang", value=1))
        c.fails("PermissionDeniedError", "overwrite", id="goal", type=COUNTER, value=counter_json(component, 2),
                sa="language")
        c.fails("PermissionDeniedError", "delete", id="goal", sa="language")
        assert py.get("goal", Counter).value == 1, "a refused write changes nothing"
        # Reads are open to everyone.
        assert c.ok("get", id="goal", type=COUNTER, sa="language")["value"] == counter_json("pylang", 1)
    finally:
        py._cast_close()
    assert c.quit() == 0
