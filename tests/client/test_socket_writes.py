"""Writes on the shared-memory session's socket: WRITES and REPLIES frames (docs/client-protocol.md).

A real server on port 0 (in a thread of this process, on its host) with
shared memory on; a raw session opened by hand plays the client, so that
each frame is what the test says; components over gRPC watch, lock and
write beside it. The C++ client's use of these frames is tested in
cpp_client/tests/server/socket_writes_test.cc.
"""

from __future__ import annotations

import mmap
import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.core.records import Identity
from cast.server.socket_writes import MAX_HELD, MAX_UNSENT, REQUESTS_PER_TURN
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import entry_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire import shared_memory as wire
from tests.client.shm_host import BYTES_VALUE, MIB, Host, image
from tests.conftest import wait_for

TYPE_URL = "type.googleapis.com/" + BYTES_VALUE


def session_socket(h: Host, token: str) -> socket.socket:
    """A connection to ``h``'s shared-memory socket, found as a client finds it (DescribeSystem)."""
    info = dir_grpc.DirectoryStub(h.channel).DescribeSystem(
        dir_pb2.DescribeSystemRequest(), metadata=(("authorization", f"Bearer {token}"),)).shared_memory
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(10)
    sock.connect("\0" + info.socket)
    return sock


class RawSession:
    """A session opened by hand: HELLO, WELCOME, then WRITES out and frames in, as a client library does."""

    def __init__(self, h: Host, token: str) -> None:
        self.sock = session_socket(h, token)
        self.reader = wire.FrameReader()
        self.frames: list[wire.Frame] = []
        self.extra: list[wm_pb2.WriteReply] = []  # replies read past those asked for
        wire.send(self.sock, wire.hello(token))
        welcome = self.next_frame()
        assert welcome.kind == wire.WELCOME, welcome
        _, self.id, _, _, _, size = wire.parse_welcome(welcome.body)
        assert welcome.fd is not None
        self.staging = mmap.mmap(welcome.fd, size)
        os.close(welcome.fd)
        self.staged_at = 0

    def next_frame(self) -> wire.Frame:
        while not self.frames:
            data, fds = wire.receive(self.sock)
            if not data:
                raise EOFError("the server closed the session")
            self.frames.extend(self.reader.feed(data, fds))
        return self.frames.pop(0)

    def replies(self, count: int) -> list[wm_pb2.WriteReply]:
        """The next ``count`` replies, in the order they came (SEGMENT frames skipped)."""
        out = self.extra
        while len(out) < count:
            frame = self.next_frame()
            if frame.fd is not None:
                os.close(frame.fd)
            if frame.kind == wire.REPLIES:
                out.extend(wm_pb2.WriteReplies.FromString(frame.body).replies)
            else:
                assert frame.kind in (wire.SEGMENT, wire.RETIRE), frame
        out, self.extra = out[:count], out[count:]
        return out

    def write(self, *requests: wm_pb2.WriteRequest) -> None:
        wire.send(self.sock, wire.writes(wm_pb2.WriteRequests(requests=requests).SerializeToString()))

    def stage(self, value: BytesValue) -> wm_pb2.StagedValue:
        data = value.SerializeToString()
        offset = self.staged_at
        self.staging[offset:offset + len(data)] = data
        self.staged_at += (len(data) + 4095) // 4096 * 4096
        return wm_pb2.StagedValue(session=self.id, offset=offset, size=len(data))

    def close(self) -> None:
        self.staging.close()
        self.sock.close()


@pytest.fixture
def host(tmp_path: Path) -> Iterator[Callable[..., Host]]:
    made: list[Host] = []

    def make() -> Host:
        made.append(Host(tmp_path))
        return made[-1]

    yield make
    for h in made:
        h.close()


@pytest.fixture
def raw(host: Callable[..., Host]) -> Iterator[Callable[..., tuple[Host, RawSession]]]:
    made: list[RawSession] = []

    def make(h: Host | None = None, cid: str = "writer", ttl: float = 0) -> tuple[Host, RawSession]:
        h = h or host()
        made.append(RawSession(h, h.signer.issue(Identity(cid, "vision"), ttl)))
        return h, made[-1]

    yield make
    for s in made:
        s.close()


def get(request_id: int, entry_id: str, read_call: int = 0) -> wm_pb2.WriteRequest:
    request = wm_pb2.WriteRequest(id=request_id, read_call=read_call)
    request.get.address.subarchitecture, request.get.address.id = "vision", entry_id
    return request


def add(request_id: int, entry_id: str, data: bytes | None = None, staged: wm_pb2.StagedValue | None = None,
        overwrite: bool = False) -> wm_pb2.WriteRequest:
    request = wm_pb2.WriteRequest(id=request_id)
    body = request.overwrite if overwrite else request.add
    body.address.subarchitecture, body.address.id = "vision", entry_id
    body.value.type_url = TYPE_URL
    if staged is not None:
        body.staged_value.CopyFrom(staged)
    else:
        body.value.value = BytesValue(value=data or b"").SerializeToString()
    return request


def lock(request_id: int, entry_id: str, timeout_ms: int) -> wm_pb2.WriteRequest:
    request = wm_pb2.WriteRequest(id=request_id, timeout_ms=timeout_ms)
    request.lock.address.subarchitecture, request.lock.address.id = "vision", entry_id
    request.lock.mode = entry_pb2.LOCK_MODE_O
    return request


def test_writes_on_the_socket_are_applied_once_in_order_staged_and_small_alike(raw: Any) -> None:
    h, session = raw()
    watcher = h.component("watcher")
    seen: list[tuple[int, bytes]] = []
    watcher.on_change(cast.address_filter("x", include_entry=True),
                      lambda ch: seen.append((ch.version, ch.entry(BytesValue).value.value)))
    values = [BytesValue(value=b"small 1"), image(MIB, 1), BytesValue(value=b"small 2"), image(MIB, 2)]
    session.write(add(1, "x", values[0].value), add(2, "x", staged=session.stage(values[1]), overwrite=True))
    session.write(add(3, "x", values[2].value, overwrite=True),
                  add(4, "x", staged=session.stage(values[3]), overwrite=True))
    replies = session.replies(4)
    assert [(r.id, r.WhichOneof("result")) for r in replies] == [(i, "write") for i in range(1, 5)], replies
    revisions = [r.write.revision for r in replies]
    assert revisions == sorted(revisions) and len(set(revisions)) == 4
    wait_for(lambda: len(seen) == 4, what="the four writes' events")
    assert [data for _, data in seen] == [v.value for v in values]
    assert [version for version, _ in seen] == [r.write.version for r in replies]
    assert watcher.get("x", BytesValue) == values[3]


def test_a_token_expired_on_the_socket_refuses_the_writes_after_it_and_changes_nothing(raw: Any) -> None:
    h, session = raw(ttl=1)
    session.write(add(1, "before", b"a"))
    assert session.replies(1)[0].WhichOneof("result") == "write"
    time.sleep(2.1)  # past the token's expiry (whole seconds, rounded up)
    session.write(add(2, "after", b"b"))
    (reply,) = session.replies(1)
    assert reply.id == 2 and reply.error.code == "UNAUTHENTICATED", reply
    assert "expired" in reply.error.message
    assert not h.component("reader").exists("after")


def test_a_lock_that_waits_on_the_socket_is_answered_later_while_the_writes_behind_it_are_answered(
    raw: Any, host: Any
) -> None:
    h = host()
    h.component("locker")  # its live session: locks end with it
    _, session = raw(h, "locker")
    holder = h.component("holder")
    holder.add("x", BytesValue(value=b"held"))
    holder.lock("x", cast.LockMode.O)
    session.write(lock(1, "x", 10_000), add(2, "y", b"behind the lock"))
    first = session.replies(1)
    assert [(r.id, r.WhichOneof("result")) for r in first] == [(2, "write")], first
    holder.unlock("x")
    (granted,) = session.replies(1)
    assert granted.id == 1 and granted.WhichOneof("result") == "lock" and granted.lock.depth == 1, granted


def test_a_malformed_writes_frame_is_refused_with_its_reason_and_nothing_of_it_applied(raw: Any) -> None:
    h, session = raw()
    good = wm_pb2.WriteRequests(requests=[add(1, "never", b"a")]).SerializeToString()
    wire.send(session.sock, wire.writes(good + b"\xff\xff\xff"))  # a valid request, then bytes that do not parse
    refused = session.next_frame()
    assert refused.kind == wire.REFUSED, refused
    assert b"is not a cast.v1.WriteRequests" in refused.body and b"nothing of it was applied" in refused.body
    with pytest.raises((EOFError, ConnectionResetError)):
        session.next_frame()
    assert not h.component("reader").exists("never")


def test_every_request_is_answered_with_its_result_a_batch_of_no_operations_too(raw: Any) -> None:
    _, session = raw()
    empty = wm_pb2.WriteRequest(id=1, batch=wm_pb2.BatchRequest())
    session.write(empty, add(2, "after-empty", b"x"))
    first, second = session.replies(2)
    assert (first.id, first.WhichOneof("result"), len(first.batch.results)) == (1, "batch", 0)
    assert second.WhichOneof("result") == "write"


def test_the_writes_frames_of_one_read_are_answered_in_one_replies_frame_in_order(raw: Any) -> None:
    h, session = raw()
    # Eight frames in one send of a few hundred bytes: the server reads them in one go, as it does a pipelining
    # client's, and answers them together rather than with a REPLIES frame each.
    session.sock.sendall(b"".join(
        wire.writes(wm_pb2.WriteRequests(requests=[add(i + 1, f"piped{i}", b"p")]).SerializeToString())
        for i in range(8)
    ))
    frame = session.next_frame()
    while frame.kind in (wire.SEGMENT, wire.RETIRE):
        frame = session.next_frame()
    assert frame.kind == wire.REPLIES, frame
    replies = wm_pb2.WriteReplies.FromString(frame.body).replies
    assert [r.id for r in replies] == list(range(1, 9))
    assert all(r.WhichOneof("result") == "write" for r in replies)
    assert h.component("reader").exists("piped7")


def test_the_writes_read_before_a_malformed_frame_are_applied_and_the_session_refused(raw: Any) -> None:
    h, session = raw()
    good = wire.writes(wm_pb2.WriteRequests(requests=[add(1, "before", b"a")]).SerializeToString())
    session.sock.sendall(good + wire.writes(b"\xff\xff\xff"))  # one read: a good frame, then one that does not parse
    (reply,) = session.replies(1)
    assert reply.WhichOneof("result") == "write", reply
    refused = session.next_frame()
    assert refused.kind == wire.REFUSED and b"is not a cast.v1.WriteRequests" in refused.body, refused
    assert h.component("reader").exists("before")


def test_a_writes_frame_over_its_bound_is_refused_naming_the_bound_before_any_of_it_is_read(raw: Any) -> None:
    h, session = raw()
    session.sock.sendall(struct.pack("<IB", wire.MAX_WRITES_FRAME + 1, wire.WRITES))
    refused = session.next_frame()
    assert refused.kind == wire.REFUSED, refused
    assert f"{wire.MAX_WRITES_FRAME + 1} bytes (1 to {wire.MAX_WRITES_FRAME} allowed".encode() in refused.body
    # The other frames keep the 64 KiB bound.
    _, other = raw(h, "other")
    other.sock.sendall(struct.pack("<IB", wire.MAX_FRAME + 1, wire.RELEASE))
    assert b"(1 to 65536 allowed)" in other.next_frame().body


def test_a_flood_of_writes_on_one_socket_lets_other_clients_writes_through_and_applies_every_one(
    raw: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    from cast.server import socket_writes

    h, session = raw()
    _, other = raw(h, "other")
    # The flood's later turns wait until the other write has been sent: the server (a thread of this process)
    # could otherwise apply all its turns while this thread waits for the GIL or a core, and the other write
    # would land after the last by the test's timing, not the server's. A server without turns applies the
    # whole flood in its first call, before the gate: the other write lands after the last, and this fails.
    sent = threading.Event()
    next_turn = socket_writes.SocketWrites._next_turn

    def gated(self: Any) -> None:
        if not sent.is_set():
            self._loop.call_later(0.001, self._next_turn)
        else:
            next_turn(self)

    monkeypatch.setattr(socket_writes.SocketWrites, "_next_turn", gated)
    count = 400 * REQUESTS_PER_TURN  # hundreds of turns: the other write lands among them, not after the last
    session.write(*(add(i + 1, f"flood{i}", b"f") for i in range(count)))  # one frame
    first = session.replies(1)  # the server is applying the flood
    other.write(add(1, "between", b"b"))
    sent.set()
    (between,) = other.replies(1)
    replies = first + session.replies(count - 1)
    assert [r.id for r in replies] == list(range(1, count + 1))
    assert all(r.WhichOneof("result") == "write" for r in replies)
    # Applied in turns of the loop: the other session's write went between them, not after the last.
    assert replies[0].write.revision < between.write.revision < replies[-1].write.revision


def _sent_in_order(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """What the server's loop sends, in order: "event" (a watch's batch encoded), "reply" (a REPLIES frame), and
    "applied" when the callback that applied a WRITES frame's requests returns (the server runs in this process)."""
    from cast.server import socket_writes, working_memory

    order: list[str] = []
    events, flush, drain = (working_memory._WatchStream._events, socket_writes.SocketWrites._flush,
                            socket_writes.SocketWrites._drain)

    def sent_events(self: Any, matches: Any) -> Any:
        order.append("event")
        return events(self, matches)

    def sent_replies(self: Any) -> None:
        if self._writes.ready:
            order.append("reply")
        flush(self)

    def applied(self: Any) -> None:
        drain(self)
        order.append("applied")

    monkeypatch.setattr(working_memory._WatchStream, "_events", sent_events)
    monkeypatch.setattr(socket_writes.SocketWrites, "_flush", sent_replies)
    monkeypatch.setattr(socket_writes.SocketWrites, "_drain", applied)
    return order


@pytest.mark.incompatible_with_mypyc
def test_a_writes_events_go_out_before_its_reply_on_the_socket(raw: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    h, session = raw()
    order = _sent_in_order(monkeypatch)
    watcher = h.component("watcher")
    seen: list[int] = []
    watcher.on_change(cast.address_filter("e"), lambda ch: seen.append(ch.revision))
    for i in range(5):  # the first write right after the watch was created too
        order.clear()
        session.write(add(i + 1, "e", b"v", overwrite=i > 0))
        session.replies(1)
        wait_for(lambda n=i + 1: len(seen) == n, what="the watcher's event")
        assert [o for o in order if o != "applied"] == ["event", "reply"], (i, order)


@pytest.mark.incompatible_with_mypyc
def test_one_writes_events_reach_every_socket_watcher_in_the_callback_that_applied_it_before_its_reply(
    raw: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Socket watchers are served in one pass on the loop, right after the write is applied: no watch stream's
    # task is woken, no turn of the loop comes between the write, its events and its reply.
    from cast.server.writes import woken

    h, session = raw()
    order = _sent_in_order(monkeypatch)
    seen: list[list[int]] = []
    for n in range(4):
        got: list[int] = []
        seen.append(got)
        h.component(f"watcher{n}").on_change(cast.address_filter("e"), lambda ch, got=got: got.append(ch.revision))
    tasks_woken = woken()
    for i in range(5):
        order.clear()
        session.write(add(i + 1, "e", b"v", overwrite=i > 0))
        (reply,) = session.replies(1)
        wait_for(lambda n=i + 1: all(len(got) == n for got in seen), what="every watcher's event")
        wait_for(lambda: "applied" in order, what="the end of the callback that applied the write")
        assert order == ["event"] * 4 + ["reply", "applied"], (i, order)
        assert all(got[-1] == reply.write.revision for got in seen)
    assert woken() == tasks_woken  # no watch stream's task was woken by these writes


def test_a_write_on_the_stream_sends_its_socket_watchers_events_before_its_reply_without_a_turn_of_the_loop(
    host: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    from cast.server import working_memory, writes

    h = host()
    order: list[str] = []
    events, take = working_memory._WatchStream._events, writes.Writes.take

    def sent_events(self: Any, matches: Any) -> Any:
        order.append("event")
        return events(self, matches)

    def replied(self: Any) -> Any:
        order.append("reply")
        return take(self)

    monkeypatch.setattr(working_memory._WatchStream, "_events", sent_events)
    monkeypatch.setattr(writes.Writes, "take", replied)
    seen: list[list[int]] = []
    for n in range(3):
        got: list[int] = []
        seen.append(got)
        h.component(f"watcher{n}").on_change(cast.address_filter("e"), lambda ch, got=got: got.append(ch.revision))
    monkeypatch.setenv("CAST_SHARED_MEMORY", "off")  # the writer alone (the watchers have sessions): the gRPC stream
    writer = h.component("writer")
    tasks_woken = writes.woken()
    for i in range(5):
        order.clear()
        if i == 0:
            writer.add("e", BytesValue(value=b"v"))
        else:
            writer.overwrite("e", BytesValue(value=b"v"))
        wait_for(lambda n=i + 1: all(len(got) == n for got in seen), what="every watcher's event")
        assert order == ["event"] * 3 + ["reply"], (i, order)
    assert writes.woken() == tasks_woken  # the reply did not wait a turn of the loop for watch streams' tasks


def test_a_flood_of_writes_reaches_a_socket_watcher_once_in_order_in_bounded_batches(raw: Any) -> None:
    from cast.client import shm_session
    from cast.client.watch_stream import EVENTS_METADATA
    from cast.server.working_memory import _BATCH_EVENTS

    h, session = raw()
    count = _BATCH_EVENTS + 3 * REQUESTS_PER_TURN
    session.write(*(add(i + 1, f"flood{i}", b"f") for i in range(count)))
    assert [r.WhichOneof("result") for r in session.replies(count)] == ["write"] * count
    # A watch that replays the whole flood from its first revision: more than one batch is pending at once.
    reader: shm_session.ClientSession = h.session("replayer")
    call = reader.new_call()
    batches: list[list[int]] = []
    reader.event_handlers[call.number] = lambda body: batches.append(
        [e.revision for e in wm_pb2.WatchResponse.FromString(body).events])
    create = wm_pb2.WatchRequest(create=wm_pb2.WatchCreate(watch_id=1, start_revisions={"vision": 1}, filters=[
        {"subarchitecture": "vision"}]))
    stop = threading.Event()

    def requests() -> Any:
        yield create
        stop.wait(30)

    stream = h.stub().Watch(requests(), metadata=h.metadata("replayer") + call.metadata + (EVENTS_METADATA,))
    try:
        assert next(stream).HasField("created")
        wait_for(lambda: (reader.poll(0.05), sum(map(len, batches)) >= count)[1], what="the flood's events")
        assert [len(b) for b in batches] == [_BATCH_EVENTS, count - _BATCH_EVENTS]  # the bound, then the rest
        assert [r for b in batches for r in b] == list(range(1, count + 1))  # once, in order
    finally:
        stop.set()
        stream.cancel()
        reader.close()


def _unread_replies(h: Host, session: RawSession, count: int) -> None:
    """``count`` gets of a 60 KiB entry (bytes in their replies) that ``session`` does not read: past MAX_UNSENT."""
    h.component("other").add("big", BytesValue(value=b"x" * (60 << 10)))
    session.write(*[get(i, "big") for i in range(1, count + 1)])


def test_a_client_that_leaves_much_unread_has_its_writes_held_while_its_socket_is_still_read(raw: Any) -> None:
    h, session = raw()
    link = h.link("writer")
    _unread_replies(h, session, 100)  # 6 MiB of replies: more than MAX_UNSENT waits for it
    wait_for(lambda: link.unsent > MAX_UNSENT, what="replies waiting for the client")
    session.write(add(101, "mine", b"held"))
    wait_for(lambda: link._writes is not None and len(link._writes._queue) >= 1, what="the add read, held")
    assert not h.component("reader").exists("mine")  # held: read, not applied, while the client reads nothing
    assert link._reading  # still read (for the RELEASEs a client sends meanwhile)
    # Past MAX_HELD bytes of held WRITES the socket is not read: a client flooding writes meanwhile is bounded.
    session.write(add(102, "large", b"y" * (MAX_HELD + MIB)))
    wait_for(lambda: not link._reading, what="the connection paused past MAX_HELD")
    replies = session.replies(102)  # the client reads: what was held is applied and answered, in order
    assert [r.id for r in replies] == list(range(1, 103))
    assert all(r.WhichOneof("result") != "error" for r in replies), [r.error for r in replies if r.error.code]
    assert h.component("reader").exists("mine") and h.component("reader2").exists("large")
    wait_for(lambda: link._reading, what="the connection read again")
