"""Reflection v1 (and v1alpha) that knows the registered entry types: generic tools decode entry values.

grpcurl is built by the Makefile (`make grpcurl`) from the Go module proxy; the
test fails, never skips, when it is missing.
"""

from __future__ import annotations

import json
import subprocess

import grpc
from cast_testing_pb2 import Pose
from google.protobuf import descriptor_pb2
from grpc_reflection.v1alpha import reflection_pb2

from tests.conftest import ROOT, ServerHandle

GRPCURL = ROOT / "build" / "bin" / "grpcurl"


def _reflect(channel: grpc.Channel, service: str, request: reflection_pb2.ServerReflectionRequest) -> (
    reflection_pb2.ServerReflectionResponse
):
    call = channel.stream_stream(
        f"/{service}/ServerReflectionInfo",
        request_serializer=reflection_pb2.ServerReflectionRequest.SerializeToString,
        response_deserializer=reflection_pb2.ServerReflectionResponse.FromString,
    )
    return next(iter(call(iter([request]), timeout=10)))


def test_reflection_v1_and_v1alpha_serve_services_and_registered_entry_types(server: ServerHandle) -> None:
    writer = server.connect("writer", "vision")
    writer.add("p", Pose(x=1.5, label="door"))  # registers cast_testing.proto
    writer._cast_close()
    channel = grpc.insecure_channel(server.endpoint)
    try:
        for service in ("grpc.reflection.v1.ServerReflection", "grpc.reflection.v1alpha.ServerReflection"):
            listed = _reflect(channel, service, reflection_pb2.ServerReflectionRequest(list_services=""))
            names = {s.name for s in listed.list_services_response.service}
            assert {"cast.v1.WorkingMemory", "grpc.reflection.v1.ServerReflection", "grpc.health.v1.Health"} <= names
            found = _reflect(channel, service, reflection_pb2.ServerReflectionRequest(
                file_containing_symbol="cast.testing.Pose"))
            files = [descriptor_pb2.FileDescriptorProto.FromString(b)
                     for b in found.file_descriptor_response.file_descriptor_proto]
            assert "cast_testing.proto" in [f.name for f in files], found
            missing = _reflect(channel, service, reflection_pb2.ServerReflectionRequest(
                file_containing_symbol="nobody.Knows"))
            assert missing.error_response.error_code == grpc.StatusCode.NOT_FOUND.value[0]
    finally:
        channel.close()


def test_grpcurl_lists_the_services_and_decodes_an_entry_value(server: ServerHandle) -> None:
    assert GRPCURL.exists(), f"{GRPCURL} is missing: `make grpcurl` builds it"
    writer = server.connect("writer", "vision")
    writer.add("p", Pose(x=1.5, label="door", tags=["a"]))
    writer._cast_close()
    base = [str(GRPCURL), "-plaintext", "-H", f"authorization: Bearer {server.token('tool', 'vision')}"]
    listed = subprocess.run([*base, server.endpoint, "list"], capture_output=True, text=True, timeout=60)
    assert listed.returncode == 0, listed.stderr
    assert {"cast.v1.WorkingMemory", "cast.v1.Directory", "grpc.reflection.v1.ServerReflection"} <= set(
        listed.stdout.split()), listed.stdout
    got = subprocess.run(
        [*base, "-d", json.dumps({"address": {"id": "p", "subarchitecture": "vision"}}), server.endpoint,
         "cast.v1.WorkingMemory/Get"],
        capture_output=True, text=True, timeout=60,
    )
    assert got.returncode == 0, got.stderr
    value = json.loads(got.stdout)["entry"]["value"]
    assert value == {"@type": "type.googleapis.com/cast.testing.Pose", "x": 1.5, "label": "door", "tags": ["a"]}


def test_grpcurl_describes_every_service_the_server_lists(server: ServerHandle) -> None:
    assert GRPCURL.exists(), f"{GRPCURL} is missing: `make grpcurl` builds it"
    base = [str(GRPCURL), "-plaintext", "-H", f"authorization: Bearer {server.token('tool', 'vision')}"]
    listed = subprocess.run([*base, server.endpoint, "list"], capture_output=True, text=True, timeout=60)
    assert listed.returncode == 0, listed.stderr
    services = listed.stdout.split()
    described = subprocess.run([*base, server.endpoint, "describe"], capture_output=True, text=True, timeout=60)
    assert described.returncode == 0, described.stderr
    for service in services:
        assert f"{service} is a service:" in described.stdout, described.stdout
    for method in ("grpc.reflection.v1.ServerReflection.ServerReflectionInfo",
                   "grpc.reflection.v1alpha.ServerReflection.ServerReflectionInfo", "cast.v1.WorkingMemory.Get"):
        one = subprocess.run([*base, server.endpoint, "describe", method], capture_output=True, text=True,
                             timeout=60)
        assert one.returncode == 0 and f"{method} is a method:" in one.stdout, one.stdout + one.stderr
