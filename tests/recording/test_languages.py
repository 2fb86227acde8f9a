"""A recording of C++, Java and Python writers: every value decodes through the schema recorded with it
(the registered FileDescriptorSet, via mcap-protobuf-support) to the value the writer meant, field by field."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Any

from cast_fidelity_pb2 import RichEntry
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from cast.v1.entry_pb2 import ChangeEvent
from tests.conftest import ServerHandle
from tests.interop.cpp_support import CppProcess
from tests.interop.java_support import JavaComponent, field_diffs, rich_entry
from tests.recording.conftest import RecordProcess, record, wait_recorded


def test_values_written_in_three_languages_decode_through_the_recorded_schema(
    server: ServerHandle, tmp_path: Path, recorders: list[RecordProcess]
) -> None:
    path = tmp_path / "languages.mcap"
    rec = record(server.endpoint, path, "--sa", "vision")
    recorders.append(rec)
    cpp = CppProcess("cast_test_fidelity", server.env("cwrite", "vision",
                                                      args={"mode": "write", "id": "cpp", "variant": "polygon"}))
    try:
        assert cpp.next_json(30)["ok"] and cpp.wait(30) == 0
    finally:
        cpp.close()
    java = JavaComponent(server.env("jwrite", "vision"))
    try:
        java.ready()
        java.ok("rich_write", id="java", variant="circle")
        assert java.quit() == 0
    finally:
        java.close()
    py = server.connect("pywrite", "vision")
    try:
        py.add("python", rich_entry("name"))
    finally:
        py._cast_close()
    wait_recorded(path, 3)
    assert rec.stop(signal.SIGINT) == 0, rec.stderr()

    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        decoded: dict[int, Any] = {}
        writers: dict[int, tuple[str, str]] = {}
        for schema, channel, message, value in reader.iter_decoded_messages():
            if channel.topic == "/cast/changes":
                event = ChangeEvent.FromString(message.data)
                writers[message.sequence] = (event.address.id, event.source_component)
            else:
                assert channel.topic == "/vision/cast.testing.RichEntry" and schema is not None
                assert schema.name == "cast.testing.RichEntry"
                decoded[message.sequence] = value
    assert sorted(writers.values()) == [("cpp", "cwrite"), ("java", "jwrite"), ("python", "pywrite")]
    variants = {"cpp": "polygon", "java": "circle", "python": "name"}
    for sequence, (entry_id, _) in writers.items():
        value = decoded[sequence]
        assert type(value).DESCRIPTOR.full_name == "cast.testing.RichEntry"  # built from the recorded schema
        got = RichEntry.FromString(value.SerializeToString())
        want = rich_entry(variants[entry_id])
        assert field_diffs(want, got) == [] and got == want, entry_id
