"""The compatibility promise (docs/compatibility.md): a client built from an older cast.v1 still works.

``first_message_set/cast/v1/directory.proto`` is the Directory's messages as the first clients
were built from them, before the registration carried ``library_version``. The test compiles it
into a descriptor pool of its own, so the messages it sends are exactly that older client's
bytes, and drives a current server with them: register, heartbeat, be listed, read the
directory. A second check compares the two files field by field, so that a renumbered or
retyped field fails here even before any server sees it.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import Message

from tests.conftest import ROOT, ServerHandle, wait_for

FIRST = Path(__file__).parent / "first_message_set"
CURRENT = ROOT / "proto"


def file_set(import_dir: Path, tmp: Path) -> descriptor_pb2.FileDescriptorSet:
    """cast/v1/directory.proto below ``import_dir``, with its imports, as protoc describes it."""
    out = tmp / f"{import_dir.name}.binpb"
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{import_dir}", "--include_imports",
                    f"--descriptor_set_out={out}", "cast/v1/directory.proto"], check=True)
    return descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes())


@pytest.fixture(scope="module")
def old(tmp_path_factory: pytest.TempPathFactory) -> dict[str, type[Message]]:
    """The first release's Directory messages, in a pool apart from the one the current code uses."""
    pool = descriptor_pool.DescriptorPool()
    for f in file_set(FIRST, tmp_path_factory.mktemp("first")).file:
        pool.Add(f)
    names = ["RegisterRequest", "RegisterResponse", "HeartbeatRequest", "HeartbeatResponse",
             "DescribeSystemRequest", "SystemDescription"]
    return {n: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"cast.v1.{n}")) for n in names}


def messages(fs: descriptor_pb2.FileDescriptorSet) -> dict[str, descriptor_pb2.DescriptorProto]:
    [directory] = [f for f in fs.file if f.name == "cast/v1/directory.proto"]
    return {m.name: m for m in directory.message_type}


def test_every_field_of_the_first_message_set_keeps_its_number_and_type(tmp_path: Path) -> None:
    first, now = messages(file_set(FIRST, tmp_path)), messages(file_set(CURRENT, tmp_path))
    assert "library_version" not in {f.name for f in first["RegisterRequest"].field}, "the frozen file is a new one"
    problems = []
    for name, message in first.items():
        if name not in now:
            problems.append(f"message {name} is gone")
            continue
        fields = {f.number: f for f in now[name].field}
        for field in message.field:
            same = fields.get(field.number)
            if same is None:
                problems.append(f"{name}: field {field.number} ({field.name}) is gone")
            elif (same.name, same.type, same.label, same.type_name) != (field.name, field.type, field.label,
                                                                         field.type_name):
                problems.append(f"{name}: field {field.number} was {field.name} ({field.type}), "
                                f"is {same.name} ({same.type})")
    assert problems == [], "an older client would not be understood:\n" + "\n".join(problems)


def call(channel: grpc.Channel, method: str, request: Message, reply: type[Message], token: str) -> Any:
    stub = channel.unary_unary(f"/cast.v1.Directory/{method}", request_serializer=type(request).SerializeToString,
                               response_deserializer=reply.FromString)
    return stub(request, metadata=(("authorization", f"Bearer {token}"),), timeout=10)


@pytest.fixture
def heartbeats(server: ServerHandle, old: dict[str, type[Message]]) -> Iterator[tuple[str, queue.Queue[Any]]]:
    """An older client's session: registered and kept alive with the older messages only."""
    token = server.token("elder", "vision")
    with grpc.insecure_channel(server.endpoint) as channel:
        request = old["RegisterRequest"](language="elder-lang", kind="unmanaged", pid=os.getpid(), host="old-host")
        registered = call(channel, "Register", request, old["RegisterResponse"], token)
        assert registered.session_id and registered.component_id == "elder"
        beats: queue.Queue[Any] = queue.Queue()
        beats.put(old["HeartbeatRequest"](session_id=registered.session_id, state=3))  # RUNNING
        stream = channel.stream_stream("/cast.v1.Directory/Heartbeat",
                                       request_serializer=old["HeartbeatRequest"].SerializeToString,
                                       response_deserializer=old["HeartbeatResponse"].FromString)
        done = object()
        replies = stream(iter(beats.get, done), metadata=(("authorization", f"Bearer {token}"),))
        assert next(replies).lease_ms > 0
        yield registered.session_id, beats
        beats.put(done)
        replies.cancel()


def test_an_older_client_registers_heartbeats_and_is_listed(
    server: ServerHandle, old: dict[str, type[Message]], heartbeats: tuple[str, queue.Queue[Any]]
) -> None:
    session_id, _ = heartbeats
    elder = wait_for(lambda: (c := server.components().get("elder")) and c.state == 3 and c,
                     what="the older client running in the directory")
    assert (elder.language, elder.host, elder.session_id, elder.library_version) == (
        "elder-lang", "old-host", session_id, "")
    # A current client beside it says its release; the older client reads that directory with its
    # own messages (the new field is one it does not know, and skips).
    newer = server.connect("newer", "vision")
    try:
        with grpc.insecure_channel(server.endpoint) as channel:
            seen = call(channel, "DescribeSystem", old["DescribeSystemRequest"](), old["SystemDescription"],
                        server.token("elder", "vision"))
        listed = {c.id: c for c in seen.components}
        assert {"elder", "newer"} <= set(listed)
        assert listed["newer"].language == "python" and listed["elder"].session_id == session_id
        # `cast components` shows the older client with an empty library column.
        out = subprocess.run([str(Path(sys.executable).parent / "cast"), "components", "--json",
                              "--endpoint", server.endpoint],
                             env={**os.environ, "CAST_TOKEN": server.token("tool", "vision")},
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        rows = {r["id"]: r for r in json.loads(out.stdout)}
        assert rows["elder"]["library_version"] == "" and rows["elder"]["state"] == "running"
        assert rows["newer"]["library_version"] == (ROOT / "VERSION").read_text().strip()
    finally:
        newer._cast_close()
