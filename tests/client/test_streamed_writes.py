"""Writes on the Write stream, pipelined writes, large values, against a real server.

The API-level bodies run on every transport of ``make_component``; the ones
about the stream itself (it is used, it fails and recovers like a unary call)
run over gRPC only.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import grpc
import jwt
import pytest
from cast_testing_pb2 import Pose
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.auth import TokenSigner
from cast.client.component import Component
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from cast.server.wire import wire_system
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.v1 import working_memory_pb2_grpc as wm_grpc
from tests.client.conftest import ThreadServer
from tests.conftest import OnAThread, wait_for


def test_async_writes_apply_in_call_order_and_errors_arrive_on_their_future(make_component: Any) -> None:
    c = make_component(cast.UnmanagedComponent, "w")
    ids = [c.new_id() for _ in range(200)]
    futures = [c.add_async(entry_id, Pose(x=i)) for i, entry_id in enumerate(ids)]
    revisions = [f.result(30).revision for f in futures]
    assert revisions == sorted(revisions) and len(set(revisions)) == 200
    again = c.add_async(ids[0], Pose())
    with pytest.raises(cast.AlreadyExistsError):
        again.result(30)
    version = c.get_entry(ids[1], Pose).version
    stale = c.overwrite_async(ids[1], Pose(x=-1), expected_version=version + 5)
    with pytest.raises(cast.ConsistencyError):
        stale.result(30)
    assert c.overwrite_async(ids[1], Pose(x=-2), expected_version=version).result(30).version == version + 1
    assert c.get(ids[1], Pose).x == -2


def test_stream_errors_are_the_unary_errors(make_component: Any) -> None:
    a = make_component(cast.UnmanagedComponent, "a")
    b = make_component(cast.UnmanagedComponent, "b")
    entry_id = "e1"
    a.add(entry_id, Pose())
    with pytest.raises(cast.PermissionDeniedError):
        a.add(a.new_id(), Pose(), subarchitecture="language")
    with pytest.raises(cast.NotFoundError):
        a.overwrite("missing", Pose())
    a.lock(entry_id, cast.LockMode.O)
    with pytest.raises(cast.LockedError):
        b.overwrite(entry_id, Pose(x=3))
    assert not b.try_lock(entry_id, cast.LockMode.O)
    with pytest.raises(cast.DeadlineExceededError):
        b.lock(entry_id, cast.LockMode.O, timeout=0.2)
    with pytest.raises(cast.InvalidArgumentError):
        a.batch([("add", "x", None)])
    assert a.unlock(entry_id) == 0
    assert b.lock(entry_id, cast.LockMode.O, timeout=5).depth == 1


def test_a_waiting_lock_does_not_hold_up_the_writes_behind_it(make_component: Any) -> None:
    a = make_component(cast.UnmanagedComponent, "a")
    b = make_component(cast.UnmanagedComponent, "b")
    a.add("held", Pose())
    a.lock("held", cast.LockMode.O)
    took: list[int] = []
    waiter = threading.Thread(target=lambda: took.append(b.lock("held", cast.LockMode.O, timeout=30).depth))
    waiter.start()
    wait_for(lambda: make_component.system.host._waiter_count == 1, what="b's lock waiting on the server")
    for i in range(20):  # b's own writes on the same stream go through meanwhile
        b.add(f"b{i}", Pose(x=i))
    assert not took
    a.unlock("held")
    waiter.join(10)
    assert took == [1]


def test_large_values_round_trip_and_reach_watchers(make_component: Any) -> None:
    writer = make_component(cast.UnmanagedComponent, "w")
    reader = make_component(cast.UnmanagedComponent, "r")
    got: list[bytes] = []
    reader.on_change(cast.ChangeFilter(id="image", include_entry=True),
                     lambda ch: got.append(ch.entry(BytesValue).value.value))
    image = bytes(range(256)) * (6 * 1024)  # 1.5 MiB
    writer.add("image", BytesValue(value=image))
    writer.overwrite("image", BytesValue(value=image[::-1]))
    assert reader.get("image", BytesValue).value == image[::-1]
    wait_for(lambda: len(got) == 2, what="both large changes")
    assert got == [image, image[::-1]]
    too_big = b"x" * (8 * 1024 * 1024 + 1)
    with pytest.raises(cast.InvalidArgumentError, match="max_value_bytes"):
        writer.overwrite("image", BytesValue(value=too_big))
    assert reader.get("image", BytesValue).value == image[::-1]  # the refusal changed nothing


# ----------------------------------------------------------------- gRPC only


@pytest.fixture
def remote() -> Any:
    system = wire_system("t", ["vision"])
    server = ThreadServer(system)
    made: list[Component] = []

    def make(component_id: str, token: str | None = None) -> Any:
        identity = Identity(component_id, "vision")
        assert server.running is not None
        transport = GrpcTransport(server.running.endpoint, token or server.signer.issue(identity), identity)
        component = cast.UnmanagedComponent()
        component._cast_bind(transport)
        made.append(component)
        return component

    make.server = server  # type: ignore[attr-defined]
    yield make
    for component in made:
        component._cast_close()
    if server.running is not None:
        server.stop()


def test_writes_and_locks_use_the_stream_not_the_unary_calls(remote: Any) -> None:
    c = remote("w")
    link = c._transport._server("vision")

    class Refuse:
        def __getattr__(self, name: str) -> Any:
            if name in ("Add", "Overwrite", "Delete", "Batch", "Lock", "Unlock"):
                raise AssertionError(f"unary {name} called: writes must go on the Write stream")
            return getattr(real, name)

    real, link.wm = link.wm, Refuse()
    c.add("e", Pose(x=1))
    c.overwrite("e", Pose(x=2))
    c.batch([("add", "f", Pose()), ("delete", "f", None)])
    c.lock("e", cast.LockMode.O)
    c.unlock("e")
    c.delete_entry("e")
    assert not c.exists("e")


def test_the_server_checks_the_token_of_every_request_and_of_the_stream() -> None:
    system = wire_system("t", ["vision"])
    server = ThreadServer(system)
    try:
        assert server.running is not None
        channel = grpc.insecure_channel(server.running.endpoint)
        stub = wm_grpc.WorkingMemoryStub(channel)
        request = wm_pb2.WriteRequests()
        add = request.requests.add(id=7).add
        add.address.id, add.address.subarchitecture = "e", "vision"
        add.value.Pack(Pose())
        with pytest.raises(grpc.RpcError) as refused:
            list(stub.Write(iter([request]), metadata=(("authorization", "Bearer nonsense"),)))
        assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
        # A token that expires while the stream is open refuses the requests after it, one by one.
        signer: TokenSigner = server.signer
        token = signer.issue(Identity("w", "vision"), ttl_seconds=1.5)
        sent: list[wm_pb2.WriteRequests] = [request]
        gate = threading.Event()

        def requests() -> Any:
            yield sent[0]
            gate.wait(10)
            late = wm_pb2.WriteRequests()
            late.requests.add(id=8).CopyFrom(request.requests[0])
            late.requests[0].id = 8
            late.requests[0].add.address.id = "later"
            yield late

        replies = stub.Write(requests(), metadata=(("authorization", f"Bearer {token}"),))
        first = next(replies)
        assert first.replies[0].id == 7 and first.replies[0].WhichOneof("result") == "write"
        expiry = jwt.decode(token, options={"verify_signature": False})["exp"]
        wait_for(lambda: time.time() > expiry + 0.1, what="the token to expire")
        gate.set()
        second = next(replies)
        assert second.replies[0].id == 8 and second.replies[0].error.code == "UNAUTHENTICATED"
        assert "expired" in second.replies[0].error.message
        assert not system.host.exists(Identity("w", "vision"), "vision", "later")
        channel.close()
    finally:
        server.stop()


def test_the_write_stream_verifies_its_token_once_until_it_expires() -> None:
    """Same token, same answer until it expires: one stream's requests do not each pay for verifying it.

    That an expired token is still refused for each request after its expiry:
    test_the_server_checks_the_token_of_every_request_and_of_the_stream.
    """
    system = wire_system("t", ["vision"])
    server = ThreadServer(system)
    try:
        assert server.running is not None
        signer: TokenSigner = server.signer
        verified: list[str] = []
        real = signer.verify_until

        def counting(token: str) -> tuple[Identity, float]:
            verified.append(token)
            return real(token)

        signer.verify_until = counting  # type: ignore[method-assign]
        messages = []
        for m in range(5):
            message = wm_pb2.WriteRequests()
            for i in range(10):
                add = message.requests.add(id=m * 10 + i).add
                add.address.id, add.address.subarchitecture = f"e{m}-{i}", "vision"
                add.value.Pack(Pose(x=i))
            messages.append(message)
        token = signer.issue(Identity("w", "vision"), ttl_seconds=3600)
        channel = grpc.insecure_channel(server.running.endpoint)
        stub = wm_grpc.WorkingMemoryStub(channel)
        replies = [r for out in stub.Write(iter(messages), metadata=(("authorization", f"Bearer {token}"),))
                   for r in out.replies]
        assert sorted(r.id for r in replies) == list(range(50))
        assert all(r.WhichOneof("result") == "write" for r in replies)
        assert 1 <= len(verified) <= 2  # the call's check and the first request's, not one per request
        channel.close()
    finally:
        server.stop()


def test_a_broken_stream_fails_outstanding_calls_and_the_next_write_reconnects(remote: Any) -> None:
    holder = remote("holder")
    waiter = remote("waiter")
    holder.add("e", Pose())
    holder.lock("e", cast.LockMode.O)
    waiting = OnAThread(lambda: waiter.lock("e", cast.LockMode.O, timeout=60))
    wait_for(lambda: remote.server.system.host._waiter_count == 1, what="the lock waiting on the server")
    stream = waiter._transport._server("vision").write_stream
    assert stream is not None and stream._call is not None
    stream._call.cancel()  # the stream breaks under the waiting lock, as when the connection drops
    error = waiting.raised()
    assert isinstance(error, cast.UnavailableError), error
    assert "may or may not have been applied" in str(error)
    waiter.add("after", Pose(x=9))  # a new stream
    assert waiter.get("after", Pose).x == 9


def test_many_large_values_in_flight_and_a_request_over_the_message_limit(remote: Any) -> None:
    c = remote("w")
    image = b"\x01" * (1024 * 1024)
    futures = [c.add_async(f"img{i}", BytesValue(value=image)) for i in range(64)]  # 64 MiB in flight
    assert [f.result(60).version for f in futures] == sorted(f.result().version for f in futures)
    assert c.get("img63", BytesValue).value == image
    big = b"\x02" * (7 * 1024 * 1024)
    with pytest.raises(cast.InvalidArgumentError, match="message limit of 67108864 bytes"):
        c.batch([("overwrite", f"img{i}", BytesValue(value=big)) for i in range(10)])  # 70 MiB in one request
    assert c.get("img0", BytesValue).value == image  # refused before it was sent: nothing changed
    c.overwrite("img0", BytesValue(value=big))  # and the stream goes on
