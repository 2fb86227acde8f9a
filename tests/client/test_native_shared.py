"""Lent values claimed, read and given back in C do what the pure path does: the same views, frames and errors.

cast.client._shared_native (python/cast/client/shared_native.c) is built by
the compiled build (make mypyc), where these tests run in `make test`; run
from the editable checkout they build it themselves with the C compiler, so
the C code is what they test either way. Each test runs a real
:class:`~cast.client.shm_session.ClientSession` on one end of a socket pair
(the server's end read here) twice, ``shm_session._native`` set to the C
module and to None, and compares what the server's end received.
"""

from __future__ import annotations

import gc
import os
import random
import subprocess
import sys
import threading
from collections.abc import Iterator
from types import ModuleType
from typing import Any

import pytest

from cast.client import shm_session, views
from cast.errors import InvalidArgumentError, UnavailableError
from cast.wire import shared_memory as wire
from tests.client.native_build import INSTALLED, ROOT, native_module, session_on_a_pair

SEGMENT_ID, SEGMENT_SIZE = 3, 1 << 16


@pytest.fixture(scope="module")
def native(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """The C module: the build's own, or (an editable checkout has none) built here from its source."""
    return native_module("_shared_native", tmp_path_factory)[0]


@pytest.fixture(params=["C", "pure"])
def how(request: pytest.FixtureRequest, native: ModuleType, monkeypatch: pytest.MonkeyPatch) -> str:
    """Each test once with the C module in use and once without it."""
    monkeypatch.setattr(shm_session, "_native", native if request.param == "C" else None)
    monkeypatch.setattr(views, "_native", native if request.param == "C" else None)
    return str(request.param)


class Pair:
    """A client session on one end of a socket pair; the server's end, and a segment of known bytes, here."""

    def __init__(self) -> None:
        self.server, self.session = session_on_a_pair()
        self.server.settimeout(5)
        fd = os.memfd_create("segment")
        os.write(fd, bytes(i % 251 for i in range(SEGMENT_SIZE)))
        self.session._handle(wire.Frame(wire.SEGMENT, wire.segment(SEGMENT_ID, SEGMENT_SIZE)[5:], fd))
        self._reader = wire.FrameReader()

    def frames(self) -> list[tuple[int, bytes]]:
        """The frames the server's end holds now (kind, body)."""
        self.server.setblocking(False)
        out: list[tuple[int, bytes]] = []
        try:
            while True:
                data = self.server.recv(1 << 20)
                if not data:
                    break
                out.extend((f.kind, bytes(f.body)) for f in self._reader.feed(data, []))
        except BlockingIOError:
            pass
        finally:
            self.server.settimeout(5)
        return out

    def close(self) -> None:
        self.session.close()
        self.server.close()


@pytest.fixture
def pair() -> Iterator[Pair]:
    p = Pair()
    yield p
    p.close()


def _claim(pair: Pair, how: str, *ref: int) -> tuple[memoryview, Any]:
    call = pair.session.new_call()
    return call.claimer()(*ref) if how == "C" else call.claim_at(*ref)  # type: ignore[no-any-return]


def _released(frames: list[tuple[int, bytes]]) -> list[int]:
    assert all(kind == wire.RELEASE for kind, _ in frames), frames
    return [i for _, body in frames for i in wire.parse_release(body)]


def test_the_claimer_is_the_c_one_where_the_build_has_it(how: str, pair: Pair) -> None:
    claim = pair.session.new_call().claimer()
    assert type(claim).__name__ == ("Claimer" if how == "C" else "method")


def test_a_claim_is_a_read_only_view_of_its_place_and_its_lease_gives_it_back_once(how: str, pair: Pair) -> None:
    view, lease = _claim(pair, how, SEGMENT_ID, 1000, 300, 77)
    assert view.readonly and view.tobytes() == bytes(i % 251 for i in range(1000, 1300))
    assert lease.value_id == 77 and lease.session is pair.session
    assert type(lease).__module__ == ("cast.client._shared_native" if how == "C" else "cast.client.shm_session")
    assert pair.frames() == []
    del view, lease
    gc.collect()
    assert _released(pair.frames()) == [77]
    gc.collect()
    assert pair.frames() == []  # once


def test_every_sixty_fourth_claim_of_a_call_says_received(how: str, pair: Pair) -> None:
    call = pair.session.new_call()
    claim = call.claimer() if how == "C" else call.claim_at
    held = [claim(SEGMENT_ID, i, 1, i) for i in range(130)]
    assert call.count == 130
    frames = pair.frames()
    assert [wire.parse_received(body) for kind, body in frames if kind == wire.RECEIVED] == [
        (call.number, 64, False), (call.number, 128, False)]
    del held
    gc.collect()
    assert sorted(_released([f for f in pair.frames() if f[0] == wire.RELEASE])) == list(range(130))


def test_a_place_past_the_segment_is_refused_as_the_pure_path_says_and_still_given_back(
    how: str, pair: Pair
) -> None:
    with pytest.raises(UnavailableError, match=rf"bytes {SEGMENT_SIZE - 10}\.\.{SEGMENT_SIZE + 10} of shared-memory "
                                               rf"segment {SEGMENT_ID}, which has {SEGMENT_SIZE}: read again"):
        _claim(pair, how, SEGMENT_ID, SEGMENT_SIZE - 10, 20, 5)
    gc.collect()
    assert _released(pair.frames()) == [5]


def test_a_segment_that_never_came_is_waited_for_then_refused(
    how: str, pair: Pair, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(shm_session, "_SEGMENT_WAIT_S", 0.2)
    with pytest.raises(UnavailableError, match="shared-memory segment 9 of the server at test did not arrive"):
        _claim(pair, how, 9, 0, 10, 6)
    gc.collect()
    assert _released(pair.frames()) == [6]


def test_a_segment_that_comes_while_the_claim_waits_is_used(how: str, pair: Pair) -> None:
    fd = os.memfd_create("late")
    os.write(fd, b"late" * 8)
    wire.send(pair.server, wire.segment(11, 32), fd)
    os.close(fd)
    view, _ = _claim(pair, how, 11, 4, 8, 8)
    assert view.tobytes() == b"latelate"


def test_a_lease_ended_while_another_thread_sends_is_sent_by_that_thread(how: str, pair: Pair) -> None:
    session = pair.session
    view, lease = _claim(pair, how, SEGMENT_ID, 0, 8, 41)
    session._send_lock.acquire()  # as a thread in the middle of a send
    try:
        del view, lease
        gc.collect()
        assert pair.frames() == []  # queued, not sent past the lock
        assert list(session._unsent) == [41]
    finally:
        session._sent()  # the sending thread lets go: what was given back meanwhile goes out
    assert _released(pair.frames()) == [41]


def test_a_lease_ended_behind_others_waiting_goes_out_with_them_in_one_frame(how: str, pair: Pair) -> None:
    session = pair.session
    view, lease = _claim(pair, how, SEGMENT_ID, 0, 8, 42)
    session._unsent.extend([1, 2])
    del view, lease
    gc.collect()
    assert pair.frames() == [(wire.RELEASE, wire.release([1, 2, 42])[5:])]


def test_a_write_held_back_goes_out_after_the_release(how: str, pair: Pair) -> None:
    session = pair.session
    view, lease = _claim(pair, how, SEGMENT_ID, 0, 8, 43)
    session._send_lock.acquire()
    session.held_writes.append(b"request")
    del view, lease
    gc.collect()
    session._sent()
    assert pair.frames() == [(wire.RELEASE, wire.release([43])[5:]), (wire.WRITES, b"request")]


def test_a_lease_ended_on_a_full_socket_waits_for_room_and_arrives_whole(how: str, pair: Pair) -> None:
    session = pair.session
    view, lease = _claim(pair, how, SEGMENT_ID, 0, 8, 1001)
    filled = 0
    while True:  # fill the socket: the RELEASE finds no room
        try:
            filled += session._sock.send(b"\0" * 4096)
        except BlockingIOError:
            break
    frame = wire.release([1001])
    got = bytearray()

    def read_later() -> None:  # the server reads a moment after the RELEASE found the socket full
        threading.Event().wait(0.3)
        while len(got) < filled + len(frame):
            got.extend(pair.server.recv(1 << 20))

    reader = threading.Thread(target=read_later)
    reader.start()
    del view, lease
    gc.collect()  # returns once the frame is written: the pure path's wait for room
    reader.join(10)
    assert not session.dead
    assert bytes(got) == b"\0" * filled + frame


def test_a_lease_of_a_session_that_ended_sends_nothing_and_raises_nothing(how: str, pair: Pair) -> None:
    view, lease = _claim(pair, how, SEGMENT_ID, 0, 8, 44)
    pair.session.close()
    del view, lease
    gc.collect()
    assert pair.server.recv(100) == b""  # the session's end closed the socket: nothing was written


def test_a_lease_made_directly_has_the_pure_leases_fields(native: ModuleType, pair: Pair) -> None:
    lease = native.Lease(pair.session, 2**64 - 1)
    assert (lease.session, lease.value_id) == (pair.session, 2**64 - 1)
    with pytest.raises(OverflowError):
        native.Lease(pair.session, 2**64)
    del lease
    gc.collect()
    assert _released(pair.frames()) == [2**64 - 1]


# ------------------------------------------------------------------------------------------------- field_of


def _fields(data: bytes, number: int, native: ModuleType) -> tuple[str, Any]:
    """What each path makes of field ``number`` of ``data``: ("ok", bytes) or ("error", message)."""
    view = memoryview(data).toreadonly()
    try:
        pure: tuple[str, Any] = ("ok", views.field_of(view, number).tobytes())
    except InvalidArgumentError as exc:
        pure = ("error", exc.message)
    fast = native.field_of(view, number)
    if fast is None:
        return ("declined", pure)
    assert fast.readonly and fast.obj is view.obj
    return ("ok", fast.tobytes())


def test_field_of_reads_what_the_pure_path_reads(native: ModuleType) -> None:
    image = b"\x0a\x80\x80\x04" + bytes(range(256)) * 256  # a BytesValue of 64 KiB: a three-byte length
    cases = [
        (image, 1), (image, 2), (b"", 1), (b"\x0a\x00", 1), (b"\x0a\x01a\x0a\x02bc", 1),  # last wins
        (b"\x08\x96\x01\x12\x03abc", 2), (b"\x09" + b"\0" * 8 + b"\x12\x01x", 2), (b"\x0d\0\0\0\0\x12\x01y", 2),
        (b"\x08\x01", 1), (b"\x09\0\0\0\0\0\0\0\0", 1), (b"\x0a\x05abc", 1), (b"\x0a", 1), (b"\x0b", 1),
        (b"\x0a\x01a", -1), (b"\x0a\x01a", 2**70), (b"\xff" * 10 + b"\x01", 1), (b"\x80" * 9 + b"\x01", 1),
    ]
    got = {(data, number): _fields(data, number, native) for data, number in cases}
    for (data, number), (answer, value) in got.items():
        pure = memoryview(data).toreadonly()
        try:
            expected: tuple[str, Any] = ("ok", views.field_of(pure, number).tobytes())
        except InvalidArgumentError as exc:
            expected = ("error", exc.message)
        if answer == "ok":
            assert (answer, value) == expected, (data.hex(), number)
        else:  # left to the pure path: what it refuses, and numbers and varints past 64 bits
            assert value == expected and (expected[0] == "error" or number < 0 or number >= 2**63
                                          or data.startswith(b"\xff" * 9)), (data.hex(), number)
    assert [answer for answer, _ in list(got.values())[:8]] == ["ok"] * 8  # well-formed: read by C


def test_field_of_agrees_on_messages_with_bytes_changed(native: ModuleType) -> None:
    rng = random.Random(5)
    base = b"\x08\x96\x01\x12\x03abc\x19" + b"\x07" * 8 + b"\x25\x01\x02\x03\x04\x0a\x04pqrs"
    read = 0
    for _ in range(5000):
        data = bytearray(base)
        for _ in range(rng.randint(1, 3)):
            data[rng.randrange(len(data))] = rng.randrange(256)
        number = rng.choice([1, 2, 3, 4, 5])
        view = memoryview(bytes(data)).toreadonly()
        fast = native.field_of(view, number)
        try:
            pure = views.field_of(view, number).tobytes()
        except InvalidArgumentError:
            assert fast is None, (data.hex(), number)
            continue
        read += fast is not None
        assert fast is None or fast.tobytes() == pure, (data.hex(), number)
    assert read > 1000  # most changed messages were read by C, not declined


def test_a_view_reads_its_field_either_way_and_refuses_alike(how: str) -> None:
    from cast.core.records import EntryRecord

    record = EntryRecord("sa", "img", "cast.v1.BytesValue", b"\x0a\x03abc\x10\x01", 1, "c", 0, 1)
    view = views.ValueView(record)
    assert view.field(1).tobytes() == b"abc" and view.field(1).readonly
    with pytest.raises(InvalidArgumentError, match="entry 'img' in subarchitecture 'sa': field 2 is a number"):
        view.field(2)
    view.release()
    with pytest.raises(InvalidArgumentError, match="this view was released"):
        view.field(1)


@pytest.mark.parametrize("setting", ["", "0"])
def test_the_build_decides_and_one_setting_turns_it_off(setting: str) -> None:
    """Native in the compiled build (pure in an editable checkout); CAST_NATIVE_SHARED=0 keeps the pure path."""
    env = {k: v for k, v in os.environ.items() if k != "CAST_NATIVE_SHARED"}
    if setting:
        env["CAST_NATIVE_SHARED"] = setting
    if not INSTALLED:
        env["PYTHONPATH"] = str(ROOT / "python")
    out = subprocess.run(
        [sys.executable, "-c", "from cast.client import shm_session, views; "
                               "print(shm_session.NATIVE_SHARED, views._native is not None)"],
        env=env, capture_output=True, text=True, check=True,
    ).stdout.strip()
    assert out == f"{INSTALLED and setting != '0'} {INSTALLED and setting != '0'}"
