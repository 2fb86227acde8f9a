"""The wire contract seen by a generic client: statuses for bad input, health, reflection."""

from __future__ import annotations

from collections.abc import Iterator

import grpc
import pytest
from cast_testing_pb2 import Counter
from google.protobuf import any_pb2
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from cast.core.schemas import files_of
from cast.v1 import (
    directory_pb2,
    directory_pb2_grpc,
    entry_pb2,
    working_memory_pb2_grpc,
)
from cast.v1 import (
    working_memory_pb2 as wm,
)
from tests.conftest import ServerHandle, register_session


class Raw:
    """Plain stubs with a token: what grpcurl or any language's generated client would send."""

    def __init__(self, server: ServerHandle, component: str = "raw", sa: str = "vision") -> None:
        self.channel = grpc.insecure_channel(server.endpoint)
        self.wm = working_memory_pb2_grpc.WorkingMemoryStub(self.channel)
        self.directory = directory_pb2_grpc.DirectoryStub(self.channel)
        self.md = (("authorization", f"Bearer {server.token(component, sa)}"),)
        register_session(self.channel, self.md)  # locks need a live session

    def call(self, method, request):  # type: ignore[no-untyped-def]
        return method(request, metadata=self.md, timeout=10)

    def status(self, method, request) -> tuple[grpc.StatusCode, str]:  # type: ignore[no-untyped-def]
        with pytest.raises(grpc.RpcError) as info:
            self.call(method, request)
        return info.value.code(), info.value.details()


@pytest.fixture
def raw(server: ServerHandle) -> Iterator[Raw]:
    r = Raw(server)
    yield r
    r.channel.close()


def addr(entry_id: str, sa: str = "vision") -> entry_pb2.EntryAddress:
    return entry_pb2.EntryAddress(id=entry_id, subarchitecture=sa)


def counter_any(value: int = 1) -> any_pb2.Any:
    packed = any_pb2.Any()
    packed.Pack(Counter(value=value))
    return packed


def state(raw: Raw) -> tuple[object, ...]:
    desc = raw.call(raw.directory.DescribeSystem, directory_pb2.DescribeSystemRequest())
    entries = raw.call(raw.wm.GetByType, wm.GetByTypeRequest(subarchitecture="vision", type="cast.testing.Counter"))
    return tuple((s.name, s.revision, s.entries) for s in desc.subarchitectures), tuple(
        (e.address.id, e.version, e.value.value) for e in entries.entries
    )


def test_bad_input_gets_its_status_and_changes_nothing(raw: Raw) -> None:
    raw.call(
        raw.directory.RegisterSchemas,
        directory_pb2.RegisterSchemasRequest(files={"file": files_of(Counter.DESCRIPTOR)}),
    )
    raw.call(raw.wm.Add, wm.AddRequest(address=addr("keep"), value=counter_any()))
    before = state(raw)
    cases = [
        (raw.wm.Add, wm.AddRequest(address=addr(""), value=counter_any()), grpc.StatusCode.INVALID_ARGUMENT, "empty"),
        (
            raw.wm.Add,
            wm.AddRequest(address=addr("x" * 300), value=counter_any()),
            grpc.StatusCode.INVALID_ARGUMENT,
            "over the limit of 256",
        ),
        (
            raw.wm.Add,
            wm.AddRequest(address=addr("x", "nowhere"), value=counter_any()),
            grpc.StatusCode.NOT_FOUND,
            "no subarchitecture 'nowhere'",
        ),
        (raw.wm.Add, wm.AddRequest(address=addr("x")), grpc.StatusCode.INVALID_ARGUMENT, "no type_url"),
        (
            raw.wm.Add,
            wm.AddRequest(
                address=addr("x"), value=any_pb2.Any(type_url="type.googleapis.com/cast.testing.Counter", value=b"\x08")
            ),
            grpc.StatusCode.INVALID_ARGUMENT,
            "does not parse as cast.testing.Counter",
        ),
        (
            raw.wm.Add,
            wm.AddRequest(address=addr("keep"), value=counter_any()),
            grpc.StatusCode.ALREADY_EXISTS,
            "already exists",
        ),
        (raw.wm.Get, wm.GetRequest(address=addr("missing")), grpc.StatusCode.NOT_FOUND, "no entry 'missing'"),
        (
            raw.wm.Overwrite,
            wm.OverwriteRequest(address=addr("missing"), value=counter_any()),
            grpc.StatusCode.NOT_FOUND,
            "cannot overwrite",
        ),
        (
            raw.wm.Overwrite,
            wm.OverwriteRequest(address=addr("keep"), value=counter_any(), expected_version=7),
            grpc.StatusCode.ABORTED,
            "expected 7",
        ),
        (raw.wm.Unlock, wm.UnlockRequest(address=addr("keep")), grpc.StatusCode.FAILED_PRECONDITION, "not locked"),
        (raw.wm.Lock, wm.LockRequest(address=addr("keep")), grpc.StatusCode.INVALID_ARGUMENT, "lock mode"),
        (
            raw.wm.Batch,
            wm.BatchRequest(operations=[wm.BatchOperation()]),
            grpc.StatusCode.INVALID_ARGUMENT,
            "batch operation 0 is empty",
        ),
        (
            raw.wm.Batch,
            wm.BatchRequest(
                operations=[
                    wm.BatchOperation(add=wm.AddRequest(address=addr("new1"), value=counter_any())),
                    wm.BatchOperation(add=wm.AddRequest(address=addr("keep"), value=counter_any())),
                ]
            ),
            grpc.StatusCode.ALREADY_EXISTS,
            "batch operation 1",
        ),
        (
            raw.wm.Add,
            wm.AddRequest(
                address=addr("big"),
                value=any_pb2.Any(type_url="type.googleapis.com/x.Blob", value=b"\0" * (9 * 1024 * 1024)),
            ),
            grpc.StatusCode.INVALID_ARGUMENT,
            "over the limit of 8388608 bytes",
        ),
        (  # a well-known type is known to every server without a registration: its bytes are checked
            raw.wm.Add,
            wm.AddRequest(
                address=addr("corrupt"),
                value=any_pb2.Any(type_url="type.googleapis.com/google.protobuf.StringValue", value=b"\xff" * 4),
            ),
            grpc.StatusCode.INVALID_ARGUMENT,
            "does not parse as google.protobuf.StringValue",
        ),
    ]
    for method, request, code, words in cases:
        got_code, details = raw.status(method, request)
        assert got_code == code, (request, details)
        assert words in details, details
    assert state(raw) == before


def test_unlock_by_non_holder_over_the_wire(server: ServerHandle, raw: Raw) -> None:
    raw.call(raw.wm.Add, wm.AddRequest(address=addr("x"), value=counter_any()))
    raw.call(raw.wm.Lock, wm.LockRequest(address=addr("x"), mode=entry_pb2.LOCK_MODE_OD))
    other = Raw(server, "other")
    code, details = other.status(other.wm.Unlock, wm.UnlockRequest(address=addr("x")))
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "locked by 'raw'" in details
    code, details = other.status(
        other.wm.Lock, wm.LockRequest(address=addr("x"), mode=entry_pb2.LOCK_MODE_O, no_wait=True)
    )
    assert code == grpc.StatusCode.FAILED_PRECONDITION
    with pytest.raises(grpc.RpcError) as info:  # a blocking lock gives up at its deadline
        other.wm.Lock(wm.LockRequest(address=addr("x"), mode=entry_pb2.LOCK_MODE_O), metadata=other.md, timeout=0.3)
    assert info.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    assert raw.call(raw.wm.Unlock, wm.UnlockRequest(address=addr("x"))).depth == 0
    other.channel.close()


def test_watch_resume_and_refusals_over_the_wire(raw: Raw) -> None:
    for i in range(3):
        raw.call(raw.wm.Add, wm.AddRequest(address=addr(f"e{i}"), value=counter_any(i)))
    requests = [
        wm.WatchRequest(
            create=wm.WatchCreate(
                watch_id=1, filters=[entry_pb2.ChangeFilter(subarchitecture="vision")], start_revisions={"vision": 2}
            )
        ),
        wm.WatchRequest(create=wm.WatchCreate(watch_id=2, filters=[entry_pb2.ChangeFilter(subarchitecture="nope")])),
    ]
    stream = raw.wm.Watch(iter(requests), metadata=raw.md, timeout=10)
    got = []
    for resp in stream:
        got.append(resp)
        if len(got) == 3:
            break
    stream.cancel()
    kinds = sorted("created" if r.HasField("created") else "failed" if r.HasField("failed") else "events" for r in got)
    assert kinds == ["created", "events", "failed"]
    failed = next(r.failed for r in got if r.HasField("failed"))
    assert (failed.watch_id, failed.code) == (2, "NOT_FOUND")
    events = next(r.events for r in got if r.events)
    assert [(e.revision, e.address.id, list(e.watch_ids)) for e in events] == [(2, "e1", [1]), (3, "e2", [1])]


def test_health_and_reflection_work_without_our_protos(server: ServerHandle) -> None:
    channel = grpc.insecure_channel(server.endpoint)
    health = health_pb2_grpc.HealthStub(channel)
    assert health.Check(health_pb2.HealthCheckRequest(), timeout=10).status == health_pb2.HealthCheckResponse.SERVING
    resp = health.Check(health_pb2.HealthCheckRequest(service="cast.v1.WorkingMemory"), timeout=10)
    assert resp.status == health_pb2.HealthCheckResponse.SERVING
    db = ProtoReflectionDescriptorDatabase(channel)
    services = set(db.get_services())
    assert {"cast.v1.WorkingMemory", "cast.v1.TaskManager", "cast.v1.Directory", "grpc.health.v1.Health"} <= services
    # The reflected file is enough to build a request without our generated code.
    from google.protobuf import descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool(db)
    method = pool.FindServiceByName("cast.v1.Directory").FindMethodByName("DescribeSystem")
    req_cls = message_factory.GetMessageClass(method.input_type)
    resp_cls = message_factory.GetMessageClass(method.output_type)
    call = channel.unary_unary(
        "/cast.v1.Directory/DescribeSystem",
        request_serializer=req_cls.SerializeToString,
        response_deserializer=resp_cls.FromString,
    )
    desc = call(req_cls(), metadata=(("authorization", f"Bearer {server.token('tool', '')}"),), timeout=10)
    assert [sa.name for sa in desc.subarchitectures] == ["vision", "language", "motor"]
    channel.close()
