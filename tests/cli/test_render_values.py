"""The CLI renders every value, task data and well-known types included, or says why not; never a traceback."""

from __future__ import annotations

import base64
import json
import os
import subprocess

import grpc
from cast_testing_pb2 import Pose
from google.protobuf import any_pb2
from google.protobuf.wrappers_pb2 import StringValue

import cast
from cast.v1 import entry_pb2, working_memory_pb2, working_memory_pb2_grpc
from tests.conftest import SECRET, VENV_BIN, ServerHandle

CAST = str(VENV_BIN / "cast")


def _cli(server: ServerHandle, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([CAST, *args, "--endpoint", server.endpoint], env={**os.environ, "CAST_SECRET": SECRET},
                          capture_output=True, text=True, timeout=60)


class Holder(cast.ManagedComponent):
    """Proposes tasks and never completes them, so their entries stay."""

    def start(self) -> None:
        self.adopted: list[str] = []

    def task_adopted(self, task: cast.Task) -> None:
        self.adopted.append(task.task_id)


def test_get_and_watch_render_task_data_of_well_known_and_user_types(server: ServerHandle) -> None:
    holder = server.connect("holder", "vision", cls=Holder)
    try:
        holder.start()
        # Written first by nobody: the server knows the well-known type without a registration.
        text = holder.propose_task("say", StringValue(value="hello"))
        pose = holder.propose_task("go", Pose(x=1.5, label="door"))
        got = _cli(server, "get", "vision", text.task_id, "--json")
        assert got.returncode == 0, got.stderr
        data = json.loads(got.stdout)["value"]["data"]
        assert data == {"@type": "type.googleapis.com/google.protobuf.StringValue", "value": "hello"}, data
        got = _cli(server, "get", "vision", pose.task_id, "--json")
        assert got.returncode == 0, got.stderr
        assert json.loads(got.stdout)["value"]["data"] == {
            "@type": "type.googleapis.com/cast.testing.Pose", "x": 1.5, "label": "door"}
        # The watch replays the history: the task entries' ADD and OVERWRITE events, rendered.
        watch = _cli(server, "watch", "--sa", "vision", "--type", "cast.v1.Task", "--values", "--json", "--from",
                     "1", "--count", "4")
        assert watch.returncode == 0 and "Traceback" not in watch.stderr, watch.stderr
        rendered = [json.loads(line)["value"]["data"]["@type"] for line in watch.stdout.splitlines()]
        assert rendered.count("type.googleapis.com/google.protobuf.StringValue") == 2, watch.stdout
        assert rendered.count("type.googleapis.com/cast.testing.Pose") == 2, watch.stdout
    finally:
        holder._cast_close()


def test_a_value_that_cannot_be_rendered_is_shown_as_base64_with_the_reason(server: ServerHandle) -> None:
    # Bytes of a type nobody registered (so the server could not check them), then registered by a reader.
    channel = grpc.insecure_channel(server.endpoint)
    stub = working_memory_pb2_grpc.WorkingMemoryStub(channel)
    md = (("authorization", f"Bearer {server.token('raw', 'vision')}"),)
    value = any_pb2.Any(type_url="type.googleapis.com/cast.testing.Pose", value=b"\xff\xff\xff\xff")
    stub.Add(working_memory_pb2.AddRequest(address=entry_pb2.EntryAddress(id="bad", subarchitecture="vision"),
                                           value=value), metadata=md)
    unknown = any_pb2.Any(type_url="type.googleapis.com/nobody.Knows", value=b"\x08\x01")
    stub.Add(working_memory_pb2.AddRequest(address=entry_pb2.EntryAddress(id="odd", subarchitecture="vision"),
                                           value=unknown), metadata=md)
    channel.close()
    other = server.connect("poser", "vision")
    other.add("good", Pose(x=2))  # registers cast_testing.proto
    other._cast_close()
    got = _cli(server, "get", "vision", "bad", "--json")
    assert got.returncode == 0 and "Traceback" not in got.stderr, got.stderr
    value_json = json.loads(got.stdout)["value"]
    assert base64.b64decode(value_json["@bytes"]) == b"\xff\xff\xff\xff"
    assert "do not parse as cast.testing.Pose" in value_json["@error"], value_json
    got = _cli(server, "get", "vision", "odd", "--json")
    assert json.loads(got.stdout)["value"]["@error"] == "no schema registered for this type"
    table = _cli(server, "get", "vision", "bad")
    assert table.returncode == 0 and "do not parse" in table.stdout and "Traceback" not in table.stderr
