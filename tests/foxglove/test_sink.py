"""The Foxglove sink on its own (no CAST server): it binds port 0 and tells the port, announces the change and gap
channels at once, says once that a type without a registered schema cannot be shown, and releases its port
for the next view."""

from __future__ import annotations

from collections.abc import Callable

from cast_testing_pb2 import Pose
from mcap_protobuf.schema import build_file_descriptor_set

from cast.foxglove.address import parse_foxglove_listen
from cast.foxglove.sink import FoxgloveSink
from cast.recording.channels import ChannelMessage, value_channel
from tests.conftest import wait_for
from tests.foxglove.conftest import FoxgloveClient, port_is_free


def test_a_type_without_a_schema_is_said_once_and_not_announced(clients: Callable[[str], FoxgloveClient]) -> None:
    notes: list[str] = []
    sink = FoxgloveSink(parse_foxglove_listen("127.0.0.1:0"), "test", notes.append)
    try:
        assert sink.port != 0 and sink.url == f"ws://127.0.0.1:{sink.port}"
        client = clients(sink.url)
        client.channel("/cast/changes")
        client.channel("/cast/gaps")
        bare = value_channel("vision", "x.Unknown", b"")
        for _ in range(2):
            sink.write(ChannelMessage(bare, 1, 1, b"\x08\x01"))
        assert notes == ["no schema registered for x.Unknown in 'vision': its values are not shown (its changes are, "
                         "on /cast/changes)"]
        schema = build_file_descriptor_set(Pose).SerializeToString()
        sink.write(ChannelMessage(value_channel("vision", "cast.testing.Pose", schema), 5, 2,
                                  Pose(x=3).SerializeToString()))
        assert client.channel("/vision/cast.testing.Pose")["schemaName"] == "cast.testing.Pose"
        assert "/vision/x.Unknown" not in client.channels and sink.messages == 1
    finally:
        sink.close()
        sink.close()  # a second close does nothing
    # Free for the next view: the SDK closes its listener on its own thread, soon after close() returns.
    wait_for(lambda: port_is_free(sink.url), what="the port to be free")
