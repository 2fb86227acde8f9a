"""The Python client's writes on its shared-memory session's socket (cast.client.socket_writes).

docs/client-protocol.md, "Writes on the session's socket": a component on the
server's host sends every Write-stream request as a WRITES frame on its
session and reads the REPLIES frames; the gRPC ``Write`` stream is not opened.
A real server with shared memory (in a thread of this process, or `cast
serve` where it must hang). The frames themselves, played by hand, are
tested in test_socket_writes.py; the C++ client's use of them in
cpp_client/tests/server/socket_writes_test.cc.
"""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client import socket_writes
from cast.client.credentials import TokenSource
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from cast.v1 import working_memory_pb2 as wm_pb2
from tests.client.shm_host import MIB, Host, image
from tests.client.shm_host import host as host  # the fixture, used by name
from tests.conftest import OnAThread, start_server, wait_for


class _NoGrpcWrites:
    """A server link's stubs with every way a write takes over gRPC refused."""

    def __init__(self, real: Any) -> None:
        self._real = real

    def __getattr__(self, name: str) -> Any:
        if name in ("Write", "Add", "Overwrite", "Delete", "Batch", "Lock", "Unlock"):
            raise AssertionError(f"{name} called over gRPC: with a session, writes go on its socket")
        return getattr(self._real, name)


def _socket_only(c: Any) -> Any:
    """``c``'s link to its server, its writes over gRPC refused from now on."""
    link = c._transport._server("vision")
    link.wm = _NoGrpcWrites(link.wm)
    return link


def test_a_components_writes_go_on_its_session_and_apply_once_in_call_order(host: Callable[..., Host]) -> None:
    h = host()
    writer, watcher = h.component("w"), h.component("r")
    seen: list[tuple[int, bytes]] = []
    watcher.on_change(cast.address_filter("img", cast.Operation.ADD, cast.Operation.OVERWRITE, include_entry=True),
                      lambda ch: seen.append((ch.revision, ch.entry(BytesValue).value.value[:1])))
    link = _socket_only(writer)
    values = [image(MIB, seed=1), BytesValue(value=b"\x02" * 100)]  # staged in shared memory, and small
    writer.add("img", values[0])
    waited = [writer.overwrite("img", values[i % 2]).revision for i in range(1, 5)]
    futures = [writer.overwrite_async("img", values[i % 2]) for i in range(5, 25)]
    pipelined = [f.result(30).revision for f in futures]
    writer.batch([("add", "other", BytesValue(value=b"x")), ("delete", "other", None)])
    writer.lock("img", cast.LockMode.O)
    writer.unlock("img")
    revisions = waited + pipelined
    assert revisions == sorted(revisions) and len(set(revisions)) == len(revisions)  # applied once each, in order
    wait_for(lambda: len(seen) == 25, what="every write's event")
    assert [r for r, _ in seen] == sorted(r for r, _ in seen)
    assert [first for _, first in seen] == [values[i % 2].value[:1] for i in range(25)]
    assert watcher.get("img", BytesValue).value == values[24 % 2].value
    assert link.write_stream is not None and link.write_stream._call is None  # no gRPC call was ever opened
    session = link.shared.current()
    assert session is not None and not session.writes.outstanding.pending


def test_pipelined_writes_outstanding_when_the_component_closes_are_answered_first(host: Callable[..., Host]) -> None:
    h = host()
    writer, reader = h.component("w"), h.component("r")
    _socket_only(writer)
    writer.add("n", BytesValue(value=b"0"))
    futures = [writer.overwrite_async("n", BytesValue(value=str(i).encode())) for i in range(1, 301)]
    writer._cast_close()
    assert all(f.done() for f in futures)
    assert [f.result().revision for f in futures] == sorted(f.result().revision for f in futures)
    assert reader.get("n", BytesValue).value == b"300"


@pytest.mark.incompatible_with_mypyc  # the server's compiled modules call received and apply directly
def test_async_writes_made_while_others_are_in_flight_go_out_together_in_order(
        host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch) -> None:
    from cast.server import socket_writes as server_writes

    h = host()
    writer, reader = h.component("w"), h.component("r")
    _socket_only(writer)
    writer.add("n", BytesValue(value=b"0"))
    # The server reads the first frame and then waits for the gate: every reply comes after the last write is
    # made, so how many frames carry the 100 writes is the client's doing alone.
    gate, frames = threading.Event(), [0]
    received, apply = server_writes.SocketWrites.received, server_writes.SocketWrites.apply

    def counted(self: Any, body: bytes) -> None:
        frames[0] += 1
        received(self, body)

    def gated(self: Any) -> None:
        gate.wait(10)
        apply(self)

    monkeypatch.setattr(server_writes.SocketWrites, "received", counted)
    monkeypatch.setattr(server_writes.SocketWrites, "apply", gated)
    futures = [writer.overwrite_async("n", BytesValue(value=str(i).encode())) for i in range(1, 101)]
    # Two of 40 KiB (sent as bytes: under the 64 KiB shared-memory threshold): never held back.
    futures += [writer.overwrite_async("n", BytesValue(value=bytes([i]) * (40 << 10))) for i in (1, 2)]
    gate.set()
    revisions = [f.result(10).revision for f in futures]
    assert revisions == sorted(revisions) and len(set(revisions)) == 102
    written = frames[0]  # the reader's get goes in a frame on its own session
    assert reader.get("n", BytesValue).value == bytes([2]) * (40 << 10)
    # A request goes in one frame with those held back while more were in flight than held: frames of 1, 2,
    # 4, 8, 16 and 32 writes, then the 37 held with the first large one, then the second alone: 8 frames,
    # where one frame a write would be 102 (and, were the large ones held too, 7).
    assert written == 8, frames


def test_an_async_write_behind_a_lock_that_waits_is_sent_and_answered_meanwhile(host: Callable[..., Host]) -> None:
    h = host()
    holder, w = h.component("holder"), h.component("w")
    _socket_only(w)
    holder.add("x", BytesValue())
    holder.lock("x", cast.LockMode.O)
    waiting = OnAThread(lambda: w.lock("x", cast.LockMode.O, timeout=30))
    wait_for(lambda: h.system.host._waiter_count == 1, what="the lock waiting on the server")
    # In flight: the lock alone. Were the write held back until a reply came, it would wait for the lock.
    assert w.add_async("y", BytesValue(value=b"y")).result(10).revision > 0
    assert waiting.thread.is_alive() and h.system.host._waiter_count == 1
    holder.unlock("x")
    assert waiting.raised(10) is None


def test_a_session_that_ends_fails_its_outstanding_writes_as_unavailable_and_the_next_write_opens_another(
        host: Callable[..., Host]) -> None:
    h = host()
    holder, waiter = h.component("holder"), h.component("waiter")
    holder.add("e", BytesValue())
    holder.lock("e", cast.LockMode.O)
    link = _socket_only(waiter)
    first = link.shared.current()
    assert first is not None
    waiting = OnAThread(lambda: waiter.lock("e", cast.LockMode.O, timeout=60))
    wait_for(lambda: h.system.host._waiter_count == 1, what="the lock waiting on the server")
    assert len(first.writes.outstanding.pending) == 1
    first._sock.shutdown(socket.SHUT_RDWR)  # the connection ends under the waiting lock
    error = waiting.raised()
    assert isinstance(error, cast.UnavailableError), error
    assert "shared-memory session" in str(error) and "may or may not have been applied" in str(error)
    wait_for(lambda: h.system.host._waiter_count == 0, what="the server giving up the lock's wait")
    waiter.add("after", BytesValue(value=b"9"))  # on a new session
    assert link.shared.current() not in (None, first)
    assert holder.get("after", BytesValue).value == b"9"


def test_a_write_waits_for_what_the_grpc_stream_has_outstanding_before_it_takes_the_socket(
        host: Callable[..., Host]) -> None:
    h = host()
    holder, waiter = h.component("holder"), h.component("waiter")
    holder.add("e", BytesValue())
    holder.lock("e", cast.LockMode.O)
    link = waiter._transport._server("vision")
    session = link.shared.current()
    assert session is not None
    link.shared._session, link.shared._retry_at = None, time.monotonic() + 60  # no session for now: gRPC
    session.close()
    stream = waiter._transport._stream("vision")
    lock = wm_pb2.WriteRequest()
    lock.lock.address.id, lock.lock.address.subarchitecture, lock.lock.mode = "e", "vision", int(cast.LockMode.O)
    granted = stream.submit(lock, timeout=60)  # waits on the server, outstanding on the gRPC call
    wait_for(lambda: h.system.host._waiter_count == 1, what="the lock waiting on the server")
    link.shared._retry_at = 0.0  # a session may open again: the next write takes the socket
    done: list[int] = []
    later = threading.Thread(target=lambda: done.append(waiter.add("later", BytesValue()).revision))
    later.start()
    time.sleep(0.5)
    assert not done, "a write went on the socket while the gRPC call had a request outstanding"
    holder.unlock("e")
    later.join(10)
    assert granted.result(10).WhichOneof("result") != "error"
    assert done and link.shared.current() is not None
    assert stream._call is not None and not stream._call.outstanding.pending


def test_a_renewed_token_opens_a_new_session_for_the_writes_after_it_large_ones_too(
        host: Callable[..., Host], tmp_path: Path) -> None:
    h = host()
    identity = Identity("w", "vision")
    token_file = tmp_path / "token"
    token_file.write_text(h.signer.issue(identity) + "\n")
    writer = cast.UnmanagedComponent()
    writer._cast_bind(GrpcTransport(h.endpoint, TokenSource.from_file(str(token_file)), identity))
    h.made.append(writer)
    link = _socket_only(writer)
    writer.add("t", BytesValue(value=b"1"))
    first = link.shared.current()
    assert first is not None
    time.sleep(1.1)  # the token file is looked at once a second
    token_file.write_text(h.signer.issue(identity, ttl_seconds=7200) + "\n")
    os.utime(token_file, (time.time() + 5, time.time() + 5))
    big = image(MIB, seed=3)
    writer.overwrite("t", big)  # staged in the new session, the one it goes on
    second = link.shared.current()
    assert second is not None and second is not first and first.dead
    assert second.token != first.token
    assert h.component("r").get("t", BytesValue).value == big.value


def test_a_write_to_a_hung_server_ends_by_its_deadline_and_the_next_one_after_it_recovers(tmp_path: Path) -> None:
    server = start_server(tmp_path, {"system": "t", "subarchitectures": {"vision": {}}})
    identity = Identity("w", "vision")
    writer = cast.UnmanagedComponent()
    writer._cast_bind(GrpcTransport(server.endpoint, server.token("w", "vision"), identity, call_timeout=1.0))
    try:
        writer.add("h", BytesValue(value=b"1"))
        link = _socket_only(writer)
        first = link.shared.current()
        assert first is not None
        os.kill(server.process.pid, signal.SIGSTOP)
        try:
            started = time.monotonic()
            with pytest.raises(cast.DeadlineExceededError, match="shared-memory session"):
                writer.overwrite("h", BytesValue(value=b"2"))
            assert time.monotonic() - started < 1.0 + 1.5  # its deadline, and what a loaded machine adds
            assert first.dead  # ended: what else was outstanding on it failed with it
        finally:
            os.kill(server.process.pid, signal.SIGCONT)
        writer.overwrite("h", BytesValue(value=b"3"))
        assert writer.get("h", BytesValue).value == b"3"
        assert link.shared.current() not in (None, first)
    finally:
        writer._cast_close()
        server.stop()


def test_a_writer_that_found_another_thread_reading_reads_its_own_reply_once_that_thread_left(
        host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch) -> None:
    # A slice longer than the test's bounds: a waiting writer must be woken when the reader leaves, not
    # find out at the end of its slice that nobody reads its reply.
    monkeypatch.setattr(socket_writes, "_READ_SLICE_S", 60.0)
    h = host()
    holder, w = h.component("holder"), h.component("w")
    for entry in ("e", "f"):
        holder.add(entry, BytesValue())
        holder.lock(entry, cast.LockMode.O)
    session = w._transport._server("vision").shared.current()
    assert session is not None
    granted: list[str] = []

    def lock(entry: str) -> None:
        w.lock(entry, cast.LockMode.O, timeout=60)
        granted.append(entry)

    reader = threading.Thread(target=lock, args=("e",))
    reader.start()
    wait_for(lambda: h.system.host._waiter_count == 1, what="the first lock waiting on the server")
    follower = threading.Thread(target=lock, args=("f",))
    follower.start()
    wait_for(lambda: h.system.host._waiter_count == 2 and session.writes.followers == 1,
             what="the second lock waiting, its thread following the first")
    # Woken by the first reply, the follower finds the reader still reading (the race this is about, made
    # certain here): it follows again, and must be told when the reader leaves.
    read_until = session.read_until
    busy_once = [True]

    def read_until_busy_once(done: Callable[[], bool], wait: float) -> bool:
        if threading.current_thread() is follower and busy_once:
            busy_once.clear()
            return False
        return read_until(done, wait)

    session.read_until = read_until_busy_once  # type: ignore[method-assign]
    holder.unlock("e")  # the reading thread gets its reply and leaves
    reader.join(10)
    assert granted == ["e"]
    holder.unlock("f")  # the follower's reply: read by the follower itself, once told the reader left
    follower.join(10)
    assert granted == ["e", "f"]
