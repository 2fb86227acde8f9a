"""A recording and the live view of the same system show the same channels: topics, encodings, schema names and
schema bytes, so a file from `cast record` opens in Foxglove as the live system does, layouts included."""

from __future__ import annotations

import base64
import signal
from collections.abc import Callable
from pathlib import Path

from cast_testing_pb2 import Pose
from google.protobuf.wrappers_pb2 import StringValue

from tests.conftest import ServerHandle
from tests.foxglove.conftest import FoxgloveClient, ViewProcess, start_view
from tests.foxglove.test_cast_foxglove import CHANGES, Manager, subscribed
from tests.recording.conftest import RecordProcess, read_indexed, record, wait_recorded


def test_a_recording_has_the_live_views_topics_and_schemas(
    server: ServerHandle, tmp_path: Path, views: list[ViewProcess], recorders: list[RecordProcess],
    clients: Callable[[str], FoxgloveClient],
) -> None:
    view = start_view(server.endpoint)
    views.append(view)
    client = clients(view.url)
    path = tmp_path / "same.mcap"
    rec = record(server.endpoint, path)
    recorders.append(rec)
    writer = server.connect("w", "vision")
    manager = server.connect("m", "motor", cls=Manager)
    assert isinstance(manager, Manager)
    try:
        client.subscribe(CHANGES)
        subscribed(client, lambda i: writer.add(f"probe-{i}", StringValue(value="probe")))
        writer.add("p1", Pose(x=1, label="one"))
        manager.propose_task("drive")
        client.wait(lambda: any(c.address.subarchitecture == "motor" for c in client.decode(CHANGES)), "the task")
        wait_recorded(path, len(client.on(CHANGES)))
        assert rec.stop(signal.SIGINT) == 0, rec.stderr()
    finally:
        writer._cast_close()
        manager._cast_close()

    recorded = {c.topic: (c.message_encoding, s.encoding if s else "", s.name if s else "", s.data if s else b"")
                for s, c, _ in read_indexed(path).messages}
    assert {"/vision/google.protobuf.StringValue", "/vision/cast.testing.Pose", "/motor/cast.v1.Task",
            CHANGES} <= set(recorded)
    for topic, seen in recorded.items():
        live = client.channel(topic)
        assert seen == (live["encoding"], live["schemaEncoding"], live["schemaName"],
                        base64.b64decode(live["schema"])), topic
