"""Single-entry reads on the shared-memory session's socket: a ``get`` among the WRITES (docs/client-protocol.md).

A component with a session sends its ``get`` as a WriteRequest in a WRITES
frame and reads the entry from the REPLIES frame: the same answer as the
unary Get, at the cost of a frame each way, in order with the session's
writes, its large value lent on the read call the request names. A real
server on port 0 (in a thread of this process) with shared memory on; raw
sessions (tests/client/test_socket_writes.py) play the frames by hand.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc
import pytest
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client.credentials import TokenSource
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire import shared_memory as wire
from tests.client.shm_host import MIB, Host, image
from tests.client.test_socket_writes import add, get
from tests.client.test_socket_writes import host as host  # the fixtures, used by name
from tests.client.test_socket_writes import raw as raw
from tests.conftest import wait_for


class _NoUnaryGet:
    """A server link's stubs with the unary Get refused."""

    def __init__(self, real: Any) -> None:
        self._real = real

    def __getattr__(self, name: str) -> Any:
        if name == "Get":
            raise AssertionError("Get called over gRPC: with a session, a get goes on its socket")
        return getattr(self._real, name)


class _UnaryGets:
    """A server link's stubs that count the unary Gets made through them."""

    def __init__(self, real: Any) -> None:
        self._real = real
        self.count = 0

    def __getattr__(self, name: str) -> Any:
        if name == "Get":
            self.count += 1
        return getattr(self._real, name)


def _count_unary_gets(c: Any) -> _UnaryGets:
    """``c``'s unary Gets from now on, counted."""
    link = c._transport._server("vision")
    link.wm = counting = _UnaryGets(link.wm)
    return counting


def test_a_get_on_the_socket_answers_what_the_unary_get_does_in_order_with_the_writes_around_it(raw: Any) -> None:
    h, session = raw()
    h.component("other").add("theirs", BytesValue(value=b"t"))
    session.write(add(1, "x", b"one"), get(2, "x"), add(3, "x", b"two", overwrite=True), get(4, "x"),
                  get(5, "missing"), get(6, "theirs"))
    replies = session.replies(6)
    assert [(r.id, r.WhichOneof("result")) for r in replies] == [
        (1, "write"), (2, "get"), (3, "write"), (4, "get"), (5, "error"), (6, "get")], replies
    assert BytesValue.FromString(replies[1].get.entry.value.value).value == b"one"
    assert BytesValue.FromString(replies[3].get.entry.value.value).value == b"two"
    assert replies[3].get.entry.version == replies[2].write.version
    assert replies[4].error.code == "NOT_FOUND" and "'missing'" in replies[4].error.message
    unary = h.stub().Get(wm_pb2.GetRequest(address=replies[5].get.entry.address), metadata=h.metadata("reader"))
    assert replies[5].get == unary  # the whole entry: address, type, value, version, author, time, revision


def test_a_large_value_read_on_the_socket_is_lent_on_the_named_call_after_its_segment(raw: Any) -> None:
    h, session = raw()
    big = image(MIB, 4)
    h.component("w").add("img", big)
    session.write(get(1, "img", read_call=7), get(2, "img"))  # the second names no call: bytes
    kinds, replies = [], []
    while len(replies) < 2:
        frame = session.next_frame()
        kinds.append(frame.kind)
        if frame.fd is not None:
            os.close(frame.fd)
        if frame.kind == wire.REPLIES:
            replies.extend(wm_pb2.WriteReplies.FromString(frame.body).replies)
    assert kinds.index(wire.SEGMENT) < kinds.index(wire.REPLIES), kinds
    lent, sent = replies[0].get.entry, replies[1].get.entry
    assert lent.HasField("shared_value") and not lent.value.value and lent.shared_value.size == big.ByteSize()
    assert BytesValue.FromString(sent.value.value) == big
    assert h.shared()["lent_bytes"] == big.ByteSize()
    # The call ends having received its one reference: what was lent on it is the client's to give back.
    wire.send(session.sock, wire.received(7, 1, True))
    wire.send(session.sock, wire.release([lent.shared_value.value_id]))
    wait_for(lambda: h.shared()["lent_bytes"] == 0, what="the lent value given back")


def test_a_get_on_the_grpc_write_stream_answers_with_bytes(host: Callable[..., Host]) -> None:
    h = host()
    big = image(MIB, 5)
    h.component("w").add("img", big)
    requests = [wm_pb2.WriteRequests(requests=[get(1, "img", read_call=3), get(2, "nope")])]
    replies = list(h.stub().Write(iter(requests), metadata=h.metadata("reader"), timeout=10))
    got = [r for message in replies for r in message.replies]
    assert [(r.id, r.WhichOneof("result")) for r in got] == [(1, "get"), (2, "error")], got
    assert BytesValue.FromString(got[0].get.entry.value.value) == big
    assert got[1].error.code == "NOT_FOUND"


def test_a_components_gets_go_on_its_session_see_its_writes_in_flight_and_give_back_what_was_lent(
        host: Callable[..., Host]) -> None:
    h = host()
    c = h.component("c")
    link = c._transport._server("vision")
    link.wm = _NoUnaryGet(link.wm)
    futures = [c.overwrite_async("n", BytesValue(value=str(i).encode())) if i else c.add_async(
        "n", BytesValue(value=b"0")) for i in range(50)]
    assert c.get("n", BytesValue).value == b"49"  # sent after the 50 writes, on the same socket: it sees them all
    revisions = [f.result(10).revision for f in futures]
    assert revisions == sorted(revisions) and len(set(revisions)) == 50
    big = image(MIB, 6)
    c.overwrite("n", big)
    assert c.get("n", BytesValue) == big
    with c.get_view("n") as view:
        assert view.shared and bytes(view.field(1)) == big.value
    with pytest.raises(cast.NotFoundError, match="'gone'"):
        c.get("gone", BytesValue)
    wait_for(lambda: h.shared()["lent_bytes"] == 0, what="every lent value given back")


def test_a_renewed_token_gives_the_gets_after_it_a_new_session(host: Callable[..., Host], tmp_path: Path) -> None:
    h = host()
    identity = Identity("r", "vision")
    token_file = tmp_path / "token"
    token_file.write_text(h.signer.issue(identity, ttl_seconds=2) + "\n")
    reader = cast.UnmanagedComponent()
    reader._cast_bind(GrpcTransport(h.endpoint, TokenSource.from_file(str(token_file)), identity))
    h.made.append(reader)
    h.component("w").add("t", BytesValue(value=b"1"))
    assert reader.get("t", BytesValue).value == b"1"
    link = reader._transport._server("vision")
    first = link.shared.current()
    assert first is not None
    token_file.write_text(h.signer.issue(identity, ttl_seconds=7200) + "\n")
    os.utime(token_file, (time.time() + 5, time.time() + 5))
    time.sleep(2.1)  # the first token has expired, and the file is looked at again
    link.wm = _NoUnaryGet(link.wm)
    assert reader.get("t", BytesValue).value == b"1"
    second = link.shared.current()
    assert second is not None and second is not first and first.dead


def test_a_get_from_a_client_without_a_session_is_the_unary_call(host: Callable[..., Host],
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAST_SHARED_MEMORY", "off")
    h = host()
    c = h.component("c")
    c.add("x", BytesValue(value=b"v"))
    gets = _count_unary_gets(c)
    assert c.get("x", BytesValue).value == b"v"
    assert gets.count == 1
    with pytest.raises(grpc.RpcError):  # the server's Write stream needs a token: a get on it too
        list(h.stub().Write(iter([wm_pb2.WriteRequests(requests=[get(1, "x")])]), timeout=10))


@pytest.mark.incompatible_with_mypyc  # a compiled server's Writes cannot be patched
def test_a_get_the_session_refuses_as_unauthenticated_is_made_again_as_the_unary_call(
        host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch) -> None:
    from cast.errors import UnauthenticatedError
    from cast.server.writes import Writes

    h = host()
    c = h.component("c")
    c.add("x", BytesValue(value=b"v"))

    def expired(self: Writes) -> Identity:
        raise UnauthenticatedError("token of component 'c' expired: get a new one (`cast token`)")

    # The session's token as the server sees it expired before the client noticed its renewal.
    monkeypatch.setattr(Writes, "_identity", expired)
    assert c.get("x", BytesValue).value == b"v"
    with pytest.raises(cast.UnauthenticatedError):
        c.add("y", BytesValue(value=b"w"))  # a write on the socket is refused as well: the refusal was real


@pytest.mark.incompatible_with_mypyc  # a compiled server's SharedSocket cannot be patched
def test_a_server_that_does_not_say_it_answers_gets_on_the_socket_gets_unary_calls(
        host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch) -> None:
    from cast.server import shared_socket
    from cast.v1 import directory_pb2

    # A server of a release before reads on the socket: its SharedMemoryInfo has no ``reads``.
    info = shared_socket.SharedSocket.info

    def older(self: Any) -> directory_pb2.SharedMemoryInfo:
        answer = info(self)
        answer.reads = False
        return answer

    monkeypatch.setattr(shared_socket.SharedSocket, "info", older)
    h = host()
    c = h.component("c")
    big = image(MIB, 7)
    c.add("x", big)
    gets = _count_unary_gets(c)
    with c.get_view("x") as view:
        assert view.shared and bytes(view.field(1)) == big.value  # lent all the same, on the unary call
    assert gets.count == 1


def test_a_get_whose_session_ends_before_its_reply_is_made_again_as_the_unary_call(
        host: Callable[..., Host]) -> None:
    h = host()
    c = h.component("c")
    c.add("x", BytesValue(value=b"v"))
    link = c._transport._server("vision")
    first = link.shared.current()
    assert first is not None and first.reads
    gets = _count_unary_gets(c)
    # A frame the server refuses, ahead of the get on the same socket: the server ends the session without
    # reading the get, which this thread's own read of the socket then finds outstanding.
    wire.send(first._sock, wire.encode(99, b"?"))
    assert c.get("x", BytesValue).value == b"v"
    assert gets.count == 1 and first.dead
