"""Type fidelity: cast.testing.RichEntry written in C++ and read in Python and Java, and the reverse, field by field.

The canonical value is ``rich_entry(variant)`` (tests/interop/java_support.py); the C++
side builds the same value in cpp_client/tests/components/cast_test_fidelity.cc and
compares with protobuf's MessageDifferencer plus explicit presence and -0.0 checks.
"""

from __future__ import annotations

import json
from typing import Any

import grpc
import pytest
from cast_fidelity_pb2 import RichEntry
from google.protobuf import descriptor_pb2

from cast.v1 import directory_pb2, directory_pb2_grpc
from tests.interop.cpp_support import CppProbe, CppProcess
from tests.interop.java_support import JavaComponent, field_diffs, rich_entry

VARIANTS = ["polygon", "circle", "name"]


def fidelity(server: Any, component_id: str, mode: str, entry_id: str, variant: str) -> tuple[int, dict[str, Any]]:
    """Run cast_test_fidelity once; its exit status and its JSON result line."""
    proc = CppProcess(
        "cast_test_fidelity",
        server.env(component_id, "vision", args={"mode": mode, "id": entry_id, "variant": variant}),
    )
    try:
        result = proc.next_json(30)
        return proc.wait(30), result
    finally:
        proc.close()


@pytest.mark.parametrize("variant", VARIANTS)
def test_cpp_writes_python_reads(server: Any, variant: str) -> None:
    status, result = fidelity(server, "cwrite", "write", f"cpp-{variant}", variant)
    assert status == 0 and result["ok"], result
    py = server.connect("pyread", "vision")
    try:
        got = py.get(f"cpp-{variant}", RichEntry)
    finally:
        py._cast_close()
    want = rich_entry(variant)
    assert field_diffs(want, got) == [], f"C++ -> Python, {variant}"
    assert got == want
    assert got.WhichOneof("shape") == want.WhichOneof("shape")
    assert got.HasField("maybe") and got.maybe == 0 and not got.HasField("never")
    assert got.text.endswith("\u0000 end"), "a NUL inside a string survives"


@pytest.mark.parametrize("variant", VARIANTS)
def test_python_writes_cpp_reads(server: Any, variant: str) -> None:
    py = server.connect("pywrite", "vision")
    try:
        py.add(f"py-{variant}", rich_entry(variant))
    finally:
        py._cast_close()
    status, result = fidelity(server, "ccheck", "check", f"py-{variant}", variant)
    assert result["ok"] and result["differences"] == "", result
    assert status == 0


def test_python_to_cpp_to_python_round_trip(server: Any) -> None:
    """C++ parses the value and writes it back with unknown fields dropped: only what it understood survives."""
    py = server.connect("pyecho", "vision")
    c = CppProbe(server.env("cecho", "vision"))
    try:
        c.ready()
        for variant in VARIANTS:
            want = rich_entry(variant)
            py.add(f"orig-{variant}", want)
            c.ok("copy", "RichEntry", f"orig-{variant}", f"copy-{variant}", "-")
            echoed = py.get(f"copy-{variant}", RichEntry)
            assert field_diffs(want, echoed) == [] and echoed == want, f"Python -> C++ -> Python, {variant}"
        assert c.quit() == 0
    finally:
        py._cast_close()
        c.close()


def test_a_cpp_reader_sees_a_difference_when_there_is_one(server: Any) -> None:
    changed = rich_entry("polygon")
    changed.samples[0] += 1
    changed.region.attributes["ключ"] = "другое"
    changed.ClearField("maybe")
    changed.weights[1] = 0.0  # +0.0 instead of -0.0
    py = server.connect("pychanged", "vision")
    try:
        py.add("changed", changed)
    finally:
        py._cast_close()
    status, result = fidelity(server, "cdiff", "check", "changed", "polygon")
    assert status == 1, "a failed check fails the component"
    assert result["ok"] is False
    report = result["differences"]
    for what in ("samples", "region", "maybe", "-0.0"):
        assert what in report, f"{what} missing from the report:\n{report}"


def test_cpp_and_python_register_the_same_schema_bytes(server: Any) -> None:
    """Every language sends the same descriptor for a file, so neither registration is refused."""
    status, result = fidelity(server, "cschema", "write", "first", "circle")
    assert status == 0, result
    with grpc.insecure_channel(server.endpoint) as channel:
        stub = directory_pb2_grpc.DirectoryStub(channel)
        md = (("authorization", f"Bearer {server.token('tool', 'vision')}"),)
        schema = stub.GetSchema(directory_pb2.GetSchemaRequest(type="cast.testing.RichEntry"), metadata=md)
    assert [f.name for f in schema.files.file] == ["cast_fidelity.proto"]
    mine = descriptor_pb2.FileDescriptorProto()
    RichEntry.DESCRIPTOR.file.CopyToProto(mine)
    assert schema.files.file[0].SerializeToString(deterministic=True) == mine.SerializeToString(deterministic=True)
    py = server.connect("pyschema", "vision")
    try:
        py.add("second", rich_entry("name"))  # registers the file again, from Python: accepted
    finally:
        py._cast_close()


def test_rich_entries_between_cpp_and_java(server: Any) -> None:
    jc = JavaComponent(server.env("jrich", "vision"))
    try:
        jc.ready()
        for variant in VARIANTS:
            # C++ writes, Java reads and compares with its own canonical value.
            status, result = fidelity(server, "cwrite", "write", f"cpp-{variant}", variant)
            assert status == 0, result
            r = jc.ok("rich_check", id=f"cpp-{variant}", variant=variant)
            assert r["diffs"] == [] and r["equal"] is True, f"C++ -> Java, {variant}: {r}"
            # Java writes, C++ reads and compares with its own.
            jc.ok("rich_write", id=f"java-{variant}", variant=variant)
            status, result = fidelity(server, "ccheck", "check", f"java-{variant}", variant)
            assert status == 0 and result["ok"], f"Java -> C++, {variant}: {json.dumps(result)[:2000]}"
        assert jc.quit() == 0
    finally:
        jc.close()
