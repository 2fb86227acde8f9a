"""`cast foxglove` against a real server, seen by a real Foxglove WebSocket client: every SA's channels with their
registered schemas, live values and change records that decode to what components wrote, task decisions on their
channel, channels appearing as types do, --sa/--type, a clean stop on SIGINT and SIGTERM."""

from __future__ import annotations

import base64
import signal
import time
from collections.abc import Callable
from itertools import count
from typing import Any

import pytest
from cast_testing_pb2 import Counter, Pose
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.wrappers_pb2 import StringValue
from websockets.exceptions import ConnectionClosed

import cast
from tests.conftest import ServerHandle, wait_for
from tests.foxglove.conftest import FoxgloveClient, ViewProcess, port_is_free, start_view

CHANGES, GAPS = "/cast/changes", "/cast/gaps"


class Manager(cast.ManagedComponent):
    """Proposes tasks from the test; the decisions are cast.v1.Task changes in its SA."""


def enum_name(message: Any, field: str) -> str:
    return str(message.DESCRIPTOR.fields_by_name[field].enum_type.values_by_number[getattr(message, field)].name)


def subscribed(client: FoxgloveClient, write: Callable[[int], None], topic: str = CHANGES) -> None:
    """Write (``write(i)``, i = 0, 1, ...) until a message arrives on ``topic``, subscribed last: from then on the
    subscriptions are in force.

    The protocol does not acknowledge a subscription, and a message sent before it took effect is not delivered.
    One write per 0.2 s at most, whatever arrives meanwhile: writes must not breed writes.
    """
    seen = len(client.on(topic))
    attempts = count()
    last = -1.0

    def arrived() -> bool:
        nonlocal last
        if len(client.on(topic)) > seen:
            return True
        if time.monotonic() - last >= 0.2:
            last = time.monotonic()
            write(next(attempts))  # its result (a task, a revision) is not an answer
        return False

    client.wait(arrived, "the subscriptions to take effect")


def test_every_working_memory_is_live_with_its_schema_and_task_decisions(
    server: ServerHandle, views: list[ViewProcess], clients: Callable[[str], FoxgloveClient]
) -> None:
    writer = server.connect("w", "vision")
    boss = server.connect("boss", "language", privileged=True)
    manager = server.connect("m", "motor", cls=Manager)
    assert isinstance(manager, Manager)
    try:
        writer.add("before", Pose(x=0, label="there before the view"))
        view = start_view(server.endpoint)
        views.append(view)
        assert "loopback only" in view.first_line and view.url.startswith("ws://127.0.0.1:")
        client = clients(view.url)
        assert client.server_info["op"] == "serverInfo"

        # What a viewer needs is announced at once: the change records, the gaps, every SA's task decisions,
        # and the types the working memories hold already.
        expected = {CHANGES: "cast.v1.ChangeEvent", GAPS: "google.protobuf.Struct",
                    "/vision/cast.v1.Task": "cast.v1.Task", "/language/cast.v1.Task": "cast.v1.Task",
                    "/motor/cast.v1.Task": "cast.v1.Task", "/vision/cast.testing.Pose": "cast.testing.Pose"}
        for topic, schema_name in expected.items():
            channel = client.channel(topic)
            assert (channel["encoding"], channel["schemaEncoding"], channel["schemaName"]) == (
                "protobuf", "protobuf", schema_name)
            files = FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
            package, _, name = schema_name.rpartition(".")
            assert any(f.package == package and name in [m.name for m in f.message_type] for f in files.file)
        assert set(client.channels) == set(expected)

        client.subscribe("/vision/cast.testing.Pose", "/motor/cast.v1.Task", CHANGES)  # the barrier's last
        subscribed(client, lambda i: boss.add(f"probe-{i}", StringValue(value="probe")))
        boss.add("fence", StringValue(value="what follows is the test's"))  # after every probe: one server, in order
        start = client.wait(lambda: next((i + 1 for i, c in enumerate(client.decode(CHANGES))
                                          if c.address.id == "fence"), None), "the fence")

        writer.add("p1", Pose(x=1, label="one"))
        writer.overwrite("p1", Pose(x=2, label="two", tags=["a", "b"]))
        writer.delete_entry("p1")
        task = manager.propose_task("drive", Pose(label="there"))
        client.wait(lambda: any(enum_name(t, "state") == "TASK_STATE_ADOPTED"
                                for t in client.decode("/motor/cast.v1.Task")), "the adoption")
        manager.task_complete(task, cast.TaskOutcome.SUCCEEDED, "arrived")
        client.wait(lambda: any(enum_name(t, "state") == "TASK_STATE_COMPLETED"
                                for t in client.decode("/motor/cast.v1.Task")), "the completion")

        # Values decode through the advertised schema alone to what was written; a delete has no value.
        poses = client.wait_messages("/vision/cast.testing.Pose", 2)
        assert [(p.x, p.label, list(p.tags)) for p in client.decode("/vision/cast.testing.Pose")] == [
            (1.0, "one", []), (2.0, "two", ["a", "b"])]
        changes = client.decode(CHANGES)
        ours = [(enum_name(c, "operation"), c.address.subarchitecture, c.address.id, c.type) for c in changes[start:]]
        assert ours[:3] == [("OPERATION_ADD", "vision", "p1", "cast.testing.Pose"),
                            ("OPERATION_OVERWRITE", "vision", "p1", "cast.testing.Pose"),
                            ("OPERATION_DELETE", "vision", "p1", "cast.testing.Pose")]
        # Each value is logged at its change's commit time, as in a recording.
        times = [c.time.ToNanoseconds() for c in changes[start:start + 2]]
        assert [p.log_time for p in poses] == times
        assert [c.source_component for c in changes[start:start + 3]] == ["w", "w", "w"]

        # Task decisions: the task manager's own changes of the task's entry, decoded on the SA's Task channel.
        tasks = client.decode("/motor/cast.v1.Task")
        assert {t.name for t in tasks} == {"drive"} and {t.component for t in tasks} == {"m"}
        states = [enum_name(t, "state") for t in tasks]
        assert states.index("TASK_STATE_ADOPTED") < states.index("TASK_STATE_COMPLETED")
        assert enum_name(tasks[-1], "outcome") == "TASK_OUTCOME_SUCCEEDED" and tasks[-1].reason == "arrived"
        assert any(c.type == "cast.v1.Task" and c.address.subarchitecture == "motor" for c in changes[start:])

        # A type seen for the first time gets its channel while the viewer is connected.
        writer.add("c1", Counter(writer="w", value=1))
        client.channel("/vision/cast.testing.Counter")
        client.subscribe("/vision/cast.testing.Counter")
        subscribed(client, lambda i: writer.overwrite("c1", Counter(writer="w", value=10 + i)),
                   "/vision/cast.testing.Counter")
        writer.overwrite("c1", Counter(writer="w", value=99))
        client.wait(lambda: any(c.value == 99 for c in client.decode("/vision/cast.testing.Counter")), "99")
        assert client.channel("/vision/cast.testing.Counter")["schemaName"] == "cast.testing.Counter"
    finally:
        for c in (writer, boss, manager):
            c._cast_close()


def test_sa_and_type_choose_the_channels(
    server: ServerHandle, views: list[ViewProcess], clients: Callable[[str], FoxgloveClient]
) -> None:
    writer = server.connect("w", "vision")
    manager = server.connect("m", "motor", cls=Manager)
    assert isinstance(manager, Manager)
    try:
        view = start_view(server.endpoint, "--sa", "motor", "--type", "cast.v1.Task")
        views.append(view)
        client = clients(view.url)
        client.subscribe("/motor/cast.v1.Task", CHANGES)
        subscribed(client, lambda i: manager.propose_task(f"probe-{i}"))
        writer.add("p1", Pose(x=1))  # another SA: not shown
        manager.propose_task("drive")
        client.wait(lambda: any(t.name == "drive" for t in client.decode("/motor/cast.v1.Task")), "the task")
        assert set(client.channels) == {CHANGES, GAPS, "/motor/cast.v1.Task"}
        assert {(c.address.subarchitecture, c.type) for c in client.decode(CHANGES)} == {("motor", "cast.v1.Task")}
    finally:
        writer._cast_close()
        manager._cast_close()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_stops_the_view_cleanly_and_frees_its_port(
    server: ServerHandle, views: list[ViewProcess], clients: Callable[[str], FoxgloveClient], sig: signal.Signals
) -> None:
    view = start_view(server.endpoint)
    views.append(view)
    client = clients(view.url)
    client.channel(CHANGES)
    assert view.stop(sig) == 0, view.output()
    assert f"stopped by {sig.name}" in view.output()
    with pytest.raises(ConnectionClosed):
        client.wait(lambda: False, "the connection to close", timeout=30)
    wait_for(lambda: port_is_free(view.url), what="the port to be free")  # nothing listens there any more
