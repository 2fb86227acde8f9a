"""Type fidelity: cast.testing.RichEntry written in Java and read in Python, and the reverse, field by field."""

from __future__ import annotations

from typing import Any

import pytest
from cast_fidelity_pb2 import RichEntry

from tests.interop.java_support import JavaComponent, field_diffs, rich_entry

VARIANTS = ["polygon", "circle", "name"]


def test_the_python_canonical_value_covers_every_field() -> None:
    # Guards the test itself: every field but the one left unset on purpose is set.
    e = rich_entry("polygon")
    unset = [f.name for f in RichEntry.DESCRIPTOR.fields
             if (f.has_presence and not e.HasField(f.name)) or (not f.has_presence and not getattr(e, f.name))]
    # The oneof members not chosen, the never-set optional, and fields whose extreme value is 0.
    assert sorted(unset) == ["circle_radius", "never", "shape_name"], unset
    assert field_diffs(e, rich_entry("polygon")) == []
    assert field_diffs(e, rich_entry("circle")) == ["circle_radius (presence)", "polygon (presence)"]


def test_rich_entries_round_trip_between_java_and_python(server: Any) -> None:
    jc = JavaComponent(server.env("jrich", "vision"))
    py = server.connect("pyrich", "vision")
    try:
        jc.ready()
        for variant in VARIANTS:
            # Java writes, Python reads.
            jc.ok("rich_write", id=f"java-{variant}", variant=variant)
            got = py.get(f"java-{variant}", RichEntry)
            want = rich_entry(variant)
            assert field_diffs(want, got) == [], f"Java -> Python, {variant}"
            assert got == want
            assert got.WhichOneof("shape") == want.WhichOneof("shape")
            assert got.HasField("maybe") and got.maybe == 0 and not got.HasField("never")
            # Python writes, Java reads (and compares with its own canonical value), then echoes it back.
            py.add(f"py-{variant}", want)
            r = jc.ok("rich_check", id=f"py-{variant}", variant=variant, echo_to=f"echo-{variant}")
            assert r["diffs"] == [] and r["equal"] is True, f"Python -> Java, {variant}: {r}"
            echoed = py.get(f"echo-{variant}", RichEntry)
            assert field_diffs(want, echoed) == [] and echoed == want, f"Python -> Java -> Python, {variant}"
        # A Java reader sees a difference when there is one (the comparison can fail).
        changed = rich_entry("polygon")
        changed.samples[0] += 1
        changed.region.attributes["ключ"] = "другое"
        changed.ClearField("maybe")
        py.add("py-changed", changed)
        r = jc.ok("rich_check", id="py-changed", variant="polygon")
        assert r["equal"] is False and sorted(r["diffs"]) == ["maybe (presence)", "region", "samples"], r
        assert jc.quit() == 0
    finally:
        py._cast_close()
        jc.close()


@pytest.mark.parametrize("variant", VARIANTS)
def test_java_written_rich_entries_have_a_registered_schema(server: Any, variant: str) -> None:
    """The server parses Java-written values with the schema the Java client registered."""
    import grpc

    from cast.v1 import directory_pb2, directory_pb2_grpc

    jc = JavaComponent(server.env("jschema", "vision"))
    try:
        jc.ready()
        jc.ok("rich_write", id="r", variant=variant)
        with grpc.insecure_channel(server.endpoint) as channel:
            stub = directory_pb2_grpc.DirectoryStub(channel)
            md = (("authorization", f"Bearer {server.token('tool', 'vision')}"),)
            schema = stub.GetSchema(directory_pb2.GetSchemaRequest(type="cast.testing.RichEntry"), metadata=md)
        assert [f.name for f in schema.files.file] == ["cast_fidelity.proto"]
        assert jc.quit() == 0
    finally:
        jc.close()
