"""NUDGE and NUDGED on the shared-memory session's socket, and the versions a server serves (docs/client-protocol.md).

A client thread blocked in the socket's read (the Java client's dispatcher
thread) cannot be woken from inside its process; another thread sends NUDGE
and the server answers NUDGED, which the blocked read returns with. A real
server on port 0 (in a thread of this process); raw sessions opened by hand,
as in tests/client/test_socket_writes.py. The Java client's use of it is
tested in java_client's DispatcherReadsTest.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import socket
import struct
from collections import deque
from types import SimpleNamespace
from typing import Any

import pytest

from cast.core.records import Identity
from cast.server import shared_socket
from cast.wire import shared_memory as wire
from tests.client.test_socket_writes import add, session_socket
from tests.client.test_socket_writes import host as host  # the fixtures, used by name
from tests.client.test_socket_writes import raw as raw
from tests.conftest import wait_for


def test_the_server_says_its_version_and_answers_a_nudge_with_nudged(raw: Any) -> None:
    _, session = raw()
    wire.send(session.sock, wire.NUDGE_FRAME)
    frame = session.next_frame()
    assert (frame.kind, frame.body) == (wire.NUDGED, b""), frame
    # The session goes on as before: a write is answered.
    session.write(add(1, "after", b"a"))
    (reply,) = session.replies(1)
    assert reply.WhichOneof("result") == "write", reply


def test_welcome_carries_the_servers_version_and_hello_may_say_any_version_up_to_it(raw: Any) -> None:
    h, _ = raw()
    for version in range(1, wire.VERSION + 1):
        sock = _hello(h, "v", version)
        frame = _first_frame(sock)
        assert frame.kind == wire.WELCOME, frame
        assert wire.parse_welcome(frame.body)[0] == wire.VERSION == wire.NUDGE_VERSION
        sock.close()
    for version in (0, wire.VERSION + 1):
        refused = _first_frame(_hello(h, "v", version))
        assert refused.kind == wire.REFUSED, refused
        assert f"protocol version {version} is not served (this server speaks 1 to {wire.VERSION})".encode() \
            in refused.body


def test_the_python_client_says_version_1_so_that_servers_of_version_1_serve_it_too() -> None:
    frame = wire.hello("tok")
    assert frame[4] == wire.HELLO
    assert wire.parse_hello(frame[5:]) == (wire.HELLO_VERSION, "tok") == (1, "tok")


def test_a_nudge_with_a_body_is_refused_naming_it(raw: Any) -> None:
    _, session = raw()
    wire.send(session.sock, wire.encode(wire.NUDGE, b"xyz"))
    refused = session.next_frame()
    assert refused.kind == wire.REFUSED and b"NUDGE carries nothing, this one 3 bytes" in refused.body, refused
    with pytest.raises((EOFError, ConnectionResetError)):
        session.next_frame()


def test_a_client_that_nudges_and_never_reads_costs_the_server_no_memory(raw: Any) -> None:
    h, session = raw()
    link = _fill_with_nudged(h, session)
    # Once the socket is full the server answers no more: what waits to be sent stays one frame at most.
    assert link.unsent <= len(wire.NUDGED_FRAME), link.unsent
    # Another client is served meanwhile.
    _, other = raw(h, "other")
    other.write(add(1, "through", b"t"))
    (reply,) = other.replies(1)
    assert reply.WhichOneof("result") == "write", reply
    assert link.unsent <= len(wire.NUDGED_FRAME)


def _fill_with_nudged(h: Any, session: Any) -> Any:
    """Nudge without reading until the server's answers wait for room in the socket; the server's connection."""
    link = h.link("writer")
    session.sock.setblocking(False)
    with contextlib.suppress(BlockingIOError):  # the server stopped reading it: its answers filled the socket
        for _ in range(2000):  # far more NUDGEDs than the socket's buffers hold
            session.sock.send(wire.NUDGE_FRAME * 100)
    session.sock.setblocking(True)
    wait_for(lambda: link.unsent > 0, what="the server's answers filling the client's socket")
    return link


def test_a_session_refused_while_its_socket_is_full_gets_every_frame_whole_then_refused(raw: Any) -> None:
    h, session = raw()
    link = _fill_with_nudged(h, session)
    wire.send(session.sock, wire.encode(wire.NUDGE, b"xyz"))
    # The session ends at once (what it held is given back), though its last frames still wait for the client.
    wait_for(lambda: link.closed and not h.system.shared.sessions, what="the refused session ended")
    kinds = []
    while True:
        try:
            frame = session.next_frame()  # a frame cut short or interleaved would raise ProtocolError here
        except (EOFError, ConnectionResetError):
            break
        kinds.append(frame.kind)
        if frame.kind == wire.REFUSED:
            assert b"NUDGE carries nothing, this one 3 bytes" in frame.body, frame
    assert kinds and set(kinds[:-1]) == {wire.NUDGED} and kinds[-1] == wire.REFUSED, kinds[-5:]


def test_a_refused_client_that_never_reads_its_last_frames_is_closed_all_the_same(raw: Any) -> None:
    h, session = raw()
    link = _fill_with_nudged(h, session)
    owner = link._owner
    wire.send(session.sock, wire.encode(wire.NUDGE, b"xyz"))
    wait_for(lambda: link.closed, what="the refused session ended")
    assert owner.farewells, "its last frames wait for the client"
    # It is closed unread after a bound (_FAREWELL_S); the guard here only ends the test if it never is.
    wait_for(lambda: not owner.farewells, timeout=30, what="the unread connection closed")
    kinds = []
    with contextlib.suppress(EOFError, ConnectionResetError):
        while True:
            kinds.append(session.next_frame().kind)
    assert set(kinds) <= {wire.NUDGED, wire.REFUSED}, kinds[-5:]


@pytest.mark.incompatible_with_mypyc  # os.dup is patched in the module
@pytest.mark.parametrize("dup_fails", [False, True])
def test_a_refused_connections_last_frames_carry_their_own_descriptors_or_are_left_out(
    dup_fails: bool, monkeypatch: pytest.MonkeyPatch, tmp_path: Any
) -> None:
    # The frames still waiting when a session is refused go out after its session has let go of its
    # descriptors: each carries a duplicate; one whose duplicate cannot be made (no descriptor left)
    # is left out whole, and REFUSED still comes last.
    if dup_fails:
        monkeypatch.setattr(shared_socket.os, "dup", _no_descriptor_left)
    server_end, client_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    server_end.setblocking(False)
    memory = tmp_path / "segment"
    memory.write_bytes(b"the segment")
    fd = os.open(memory, os.O_RDONLY)

    async def farewell() -> None:
        owner = SimpleNamespace(loop=asyncio.get_running_loop(), farewells=set())
        shared_socket._Farewell(owner, server_end, deque([(wire.segment(7, 11), fd), (wire.refused("why"), None)]))
        while owner.farewells:
            await asyncio.sleep(0.01)

    try:
        asyncio.run(farewell())
        assert server_end.fileno() < 0, "the socket closed once its frames went"
        os.fstat(fd)  # the caller's descriptor is still its own, open
        reader = wire.FrameReader()
        frames: list[wire.Frame] = []
        while True:
            data, fds = wire.receive(client_end)
            if not data:
                break
            frames.extend(reader.feed(data, fds))
        assert [f.kind for f in frames] == ([wire.REFUSED] if dup_fails else [wire.SEGMENT, wire.REFUSED])
        assert frames[-1].body == b"why"
        if not dup_fails:
            sent = frames[0].fd
            assert sent is not None and sent != fd
            assert os.pread(sent, 11, 0) == b"the segment"
            os.close(sent)
    finally:
        os.close(fd)
        client_end.close()


def _no_descriptor_left(fd: int) -> int:
    """``os.dup`` in a process whose descriptor table is full."""
    raise OSError(errno.EMFILE, os.strerror(errno.EMFILE))


def _hello(h: Any, cid: str, version: int) -> socket.socket:
    """A connection to ``h``'s session socket that said HELLO with ``version``."""
    token = h.signer.issue(Identity(cid, "vision"))
    sock = session_socket(h, token)
    wire.send(sock, wire.encode(wire.HELLO, struct.pack("<H", version) + token.encode()))
    return sock


def _first_frame(sock: socket.socket) -> wire.Frame:
    """The first frame the server sends on ``sock`` (descriptors that came with frames closed)."""
    reader = wire.FrameReader()
    while True:
        data, fds = wire.receive(sock)
        if not data:
            raise EOFError("the server closed the session")
        frames = reader.feed(data, fds)
        for f in frames:
            if f.fd is not None:
                os.close(f.fd)
        if frames:
            return frames[0]
