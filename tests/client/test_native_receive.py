"""A session's socket read and its frames handed on in C do what the pure path does: the same frames, ends and turns.

cast.client._receive_native (python/cast/client/receive_native.c) is built by
the compiled build (make mypyc), where these tests run in `make test`; run
from the editable checkout they build it themselves with the C compiler, so
the C code is what they test either way. Each test runs a real
:class:`~cast.client.shm_session.ClientSession` on one end of a socket pair
(the server's end written here) twice, ``shm_session._receive`` set to the C
module and to None, and compares what the session did.
"""

from __future__ import annotations

import array
import os
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterator
from types import ModuleType
from typing import Any

import pytest

from cast.client import shm_session
from cast.errors import CastError, UnavailableError
from cast.wire import shared_memory as wire
from tests.client.native_build import native_module, session_on_a_pair


@pytest.fixture(scope="module")
def native(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """The C module: the build's own, or (an editable checkout has none) built here from its source."""
    module = native_module("_receive_native", tmp_path_factory)[0]
    module.configure(wire.Frame, wire.ProtocolError, CastError)
    return module


@pytest.fixture(params=["C", "pure"])
def how(request: pytest.FixtureRequest, native: ModuleType, monkeypatch: pytest.MonkeyPatch) -> str:
    """Each test once with the C module in use and once without it."""
    monkeypatch.setattr(shm_session, "_receive", native if request.param == "C" else None)
    return str(request.param)


class Pair:
    """A client session on one end of a socket pair, noting each frame it handles; the server's end here."""

    def __init__(self) -> None:
        self.server, self.session = session_on_a_pair()
        self.handled: list[tuple[int, bytes, bool]] = []  # kind, body, came with a descriptor
        original = self.session._handle

        def noted(frame: wire.Frame) -> None:
            self.handled.append((frame.kind, bytes(frame.body), frame.fd is not None))
            original(frame)

        self.session._handle = noted  # type: ignore[method-assign]

    def send(self, data: bytes, fd: int | None = None) -> None:
        wire.send(self.server, data, fd)

    def read(self) -> bool:
        """What the dispatcher does when the socket is readable."""
        return self.session.reader()()

    def close(self) -> None:
        self.session.close()
        self.server.close()


@pytest.fixture
def pair(how: str) -> Iterator[Pair]:
    p = Pair()
    yield p
    p.close()


def _open_fds() -> set[int]:
    return {int(name) for name in os.listdir("/proc/self/fd")}


def test_the_reader_is_the_c_one_where_the_build_has_it(how: str, pair: Pair) -> None:
    reader = pair.session.reader()
    assert (type(reader).__name__ == "partial") == (how == "C")


def test_frames_split_anywhere_across_reads_are_handed_on_whole_in_order(how: str, pair: Pair) -> None:
    frames = [wire.retire(7), wire.encode(wire.NUDGED), wire.retire(8)]
    stream = b"".join(frames)
    for cut in range(1, len(stream)):
        pair.handled.clear()
        pair.server.sendall(stream[:cut])
        assert pair.read()
        pair.server.sendall(stream[cut:])
        assert pair.read()
        assert [(k, b) for k, b, _ in pair.handled] == [
            (wire.RETIRE, (7).to_bytes(4, "little")), (wire.NUDGED, b""), (wire.RETIRE, (8).to_bytes(4, "little"))]
    assert not pair.session.dead


def test_a_segment_frame_is_handed_on_with_its_memory_file_and_mapped(how: str, pair: Pair) -> None:
    fd = os.memfd_create("segment")
    os.write(fd, b"pixels" * 100)
    pair.send(wire.segment(5, 600), fd)
    os.close(fd)
    assert pair.read()
    assert pair.handled == [(wire.SEGMENT, wire.segment(5, 600)[5:], True)]
    view, lease = pair.session.claim_at(5, 6, 6, 1)
    assert view.tobytes() == b"pixels"
    del view, lease


def test_events_frames_go_to_their_calls_handler_and_an_unknown_calls_are_dropped(how: str, pair: Pair) -> None:
    got: list[bytes] = []
    pair.session.event_handlers[3] = got.append
    pair.send(wire.events(3, b"first") + wire.events(4, b"nobody's") + wire.events(3, b"second"))
    assert pair.read()
    assert got == [b"first", b"second"]


@pytest.mark.parametrize(("data", "why"), [
    (b"\x00\x00\x00\x00\x0f", "frame of 0 bytes (1 to 67108864 allowed)"),
    ((70000).to_bytes(4, "little") + bytes([wire.RETIRE]), "frame of kind 13 has 70000 bytes (1 to 65536 allowed)"),
    ((80 << 20).to_bytes(4, "little") + bytes([wire.REPLIES]), "frame of 83886080 bytes (1 to 67108864 allowed)"),
    (wire.segment(1, 10), "frame of kind 12 came without its memory file"),
])
def test_a_frame_that_breaks_the_protocol_ends_the_session_with_the_same_words(
    how: str, pair: Pair, data: bytes, why: str
) -> None:
    pair.send(wire.retire(1) + data)
    assert pair.read()
    assert pair.session.dead == why
    assert pair.handled == []  # nothing of the read that held it


def test_memory_files_of_frames_cut_before_a_bad_one_are_closed_at_the_end(how: str, pair: Pair) -> None:
    before = _open_fds()
    fds = [os.memfd_create("t") for _ in range(2)]
    data = wire.segment(0, 4096) + wire.segment(1, 4096) + b"\x00\x00\x00\x00\x04"
    pair.server.sendmsg([data], [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", fds))])
    for fd in fds:
        os.close(fd)
    assert pair.read()
    assert pair.session.dead.startswith("frame of 0 bytes")
    assert _open_fds() <= before  # both files, received and never handed on, closed by the session's end


def test_the_server_closing_ends_the_session(how: str, pair: Pair) -> None:
    pair.server.shutdown(socket.SHUT_WR)
    assert pair.read()
    assert pair.session.dead == "the server closed the session"


def test_a_read_that_fails_ends_the_session_saying_why(how: str, pair: Pair) -> None:
    pair.session._sock.close()  # the descriptor gone under the reader: the read fails (EBADF)
    assert pair.read()
    assert pair.session.dead.startswith("read failed: [Errno 9] Bad file descriptor"), pair.session.dead


def test_a_frame_larger_than_one_read_arrives_whole(how: str, pair: Pair) -> None:
    got: list[bytes] = []
    pair.session.event_handlers[1] = got.append
    big = bytes(range(256)) * 4096  # 1 MiB: four reads of the session's 256 KiB
    sender = threading.Thread(target=pair.server.sendall, args=(wire.events(1, big),))
    sender.start()
    while not got:
        pair.session.poll(0.05)
    sender.join()
    assert got == [big]
    receiver = pair.session._receiver
    if receiver is not None:  # the room the frame took is not kept once it was handed on
        assert receiver.capacity <= 4 * shm_session._READ_BYTES, receiver.capacity


def test_reading_waits_for_no_one_and_is_refused_while_another_thread_reads(how: str, pair: Pair) -> None:
    pair.send(wire.retire(1))
    pair.session._read_lock.acquire()
    try:
        assert not pair.read()
        assert pair.handled == []
    finally:
        pair.session._read_lock.release()
    assert pair.read()
    assert [k for k, _, _ in pair.handled] == [wire.RETIRE]
    assert not pair.session.reading


def test_what_is_left_for_after_the_read_is_done_once_the_lock_is_let_go(how: str, pair: Pair) -> None:
    fd = os.memfd_create("segment")
    os.ftruncate(fd, 4096)
    pair.send(wire.segment(2, 4096), fd)
    os.close(fd)
    assert pair.read()
    pair.send(wire.retire(2))
    assert pair.read()
    assert pair.session._retired == [] and 2 not in pair.session._segments  # unmapped by _after_reading


def test_an_error_of_a_handler_reaches_the_caller_and_the_lock_is_let_go(how: str, pair: Pair) -> None:
    def broken(body: bytes) -> None:
        raise ValueError("the handler failed")

    pair.session.event_handlers[1] = broken
    pair.send(wire.events(1, b"x"))
    with pytest.raises(ValueError, match="the handler failed"):
        pair.read()
    assert not pair.session.reading and not pair.session.dead


def test_the_c_receiver_counts_its_reads_and_refuses_to_be_read_twice_at_once(native: ModuleType) -> None:
    ours, theirs = socket.socketpair()
    with ours, theirs:
        ours.setblocking(False)
        receiver = native.Receiver(ours, 1024)

        class Session:
            def __init__(self) -> None:
                self.dead = ""
                self.event_handlers: dict[int, Callable[[bytes], None]] = {}
                self.frames: list[int] = []

            def _handle(self, frame: wire.Frame) -> None:
                self.frames.append(frame.kind)
                receiver.read_available(self)

        session = Session()
        theirs.sendall(wire.retire(1))
        with pytest.raises(RuntimeError, match="called again while it reads"):
            receiver.read_available(session)
        assert receiver.reads == 1 and session.frames == [wire.RETIRE]
    with pytest.raises(ValueError, match="chunk is 0 bytes: give 1 to 67108864"):
        native.Receiver(ours, 0)


# ----------------------------------------------------------- DirectTurn


class _Stream:
    """What DirectTurn reads and sets of a WatchStream, and the pure path's calls it makes, noted."""

    def __init__(self) -> None:
        self._read: object = "read"
        self._socket_broke = ""
        self._turning = False
        self._frames: deque[bytes] = deque()
        self._frames_lock = threading.RLock()
        self.calls: list[tuple[str, Any]] = []

    def _turn_frames(self) -> None:
        self.calls.append(("turn_frames", list(self._frames)))
        self._frames.clear()

    def _turn_failed(self, exc: CastError) -> None:
        self.calls.append(("failed", exc.message))
        self._socket_broke = exc.message


def _direct(native: ModuleType, stream: _Stream, turn: Callable[..., bool], ident: int | None = None) -> Any:
    def slow_turn(body: bytes, read: object, sink: object, seen: object) -> None:
        stream.calls.append(("slow", body))

    def fallback(body: bytes) -> None:
        stream.calls.append(("frame", body))

    return native.DirectTurn(
        stream, "read", stream._frames_lock, stream._frames, "claim", "sink", {}, turn, slow_turn, fallback,
        threading.get_ident() if ident is None else ident,
    )


def test_a_frame_on_the_dispatcher_thread_is_turned_at_once(native: ModuleType) -> None:
    stream = _Stream()

    def turn(body: bytes, claim: object, sink: object, seen: object) -> bool:
        assert stream._turning and stream._frames_lock._is_owned()  # type: ignore[attr-defined]
        stream.calls.append(("turn", body))
        return True

    _direct(native, stream, turn)(b"events")
    assert stream.calls == [("turn", b"events")] and not stream._turning


@pytest.mark.parametrize("state", ["another thread", "ended call", "broken", "queued", "turning"])
def test_every_other_case_goes_to_the_pure_path(native: ModuleType, state: str) -> None:
    stream = _Stream()
    ident = threading.get_ident() + 1 if state == "another thread" else None
    if state == "ended call":
        stream._read = "another read"
    elif state == "broken":
        stream._socket_broke = "why"
    elif state == "queued":
        stream._frames.append(b"before")
    elif state == "turning":
        stream._turning = True
    _direct(native, stream, lambda *a: pytest.fail("turned"), ident)(b"events")
    assert stream.calls == [("frame", b"events")]


def test_a_frame_the_c_decoder_declines_takes_the_pure_decoder(native: ModuleType) -> None:
    stream = _Stream()
    _direct(native, stream, lambda *a: False)(b"events")
    assert stream.calls == [("slow", b"events")]


def test_a_value_that_cannot_be_claimed_breaks_the_call_as_the_pure_path_does(native: ModuleType) -> None:
    stream = _Stream()

    def turn(*args: object) -> bool:
        raise UnavailableError("segment 9 did not arrive")

    _direct(native, stream, turn)(b"events")
    assert stream.calls == [("failed", "segment 9 did not arrive")] and not stream._turning


def test_frames_queued_while_turning_are_turned_next_in_order(native: ModuleType) -> None:
    stream = _Stream()

    def turn(*args: object) -> bool:
        stream._frames.append(b"read by a claim")  # as _frame queues one while the stream turns
        return True

    _direct(native, stream, turn)(b"events")
    assert stream.calls == [("turn_frames", [b"read by a claim"])]


def test_an_error_of_the_sink_reaches_the_caller_and_the_stream_is_left_as_it_was(native: ModuleType) -> None:
    stream = _Stream()

    def turn(*args: object) -> bool:
        raise KeyError("sink")

    with pytest.raises(KeyError, match="sink"):
        _direct(native, stream, turn)(b"events")
    assert not stream._turning and not stream._frames_lock._is_owned()  # type: ignore[attr-defined]
