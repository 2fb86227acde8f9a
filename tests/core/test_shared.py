"""The server's shared memory, in the core: the arena's seals and reuse, staging, leases, the window, the bounds."""

from __future__ import annotations

import gc
import mmap
import os
import sys
import threading
import time

import pytest
from google.protobuf.wrappers_pb2 import BytesValue

from cast.core.arena import ALIGN, PAGE, SPARE_IDLE_S, Arena, Segment
from cast.core.large_fields import largest_payload
from cast.core.records import BatchOp, Identity, Limits, Operation
from cast.core.shared import SharedMemory, SharedSettings
from cast.errors import InvalidArgumentError, PermissionDeniedError

WRITER = Identity("writer", "vision")
OTHER = Identity("other", "vision")
MIB = 1 << 20


def _whole(size: int) -> bytes:
    """A value of ``size`` bytes that takes exactly its pages: no field of it to align, so no page more."""
    return bytes(size)


def memory(window: int = 64 * MIB, max_bytes: int = 1 << 30, threshold: int = 64 * 1024) -> SharedMemory:
    return SharedMemory(SharedSettings(True, threshold, max_bytes, window), Limits(max_value_bytes=8 * MIB))


def test_a_new_segment_is_faulted_in_while_other_threads_run() -> None:
    """Populating lets the GIL go: the server's loop goes on while a new segment's pages are faulted in.

    With a switch interval of seconds, a thread that kept the GIL through its
    ``madvise`` calls would hold it until the segment was done: this thread,
    which lets the GIL go every millisecond (as an event loop waiting for its
    sockets does), would not get it back meanwhile: it would run once or twice,
    where it runs about once a millisecond of the ~80 ms that 256 MiB take here.
    The segment is that large so that the count stays far from the bound on a
    fast machine (32 MiB took 9-10 ms, too close to ten turns).
    """
    interval = sys.getswitchinterval()
    sys.setswitchinterval(5.0)
    segment = Segment(9001, 256 * MIB)
    try:
        segment.populate()
        populating = [t for t in threading.enumerate() if t.name == "cast-arena-9001"]
        ran = 0
        while any(t.is_alive() for t in populating):
            time.sleep(0.001)
            ran += 1
        assert ran >= 10, f"this thread ran {ran} times while the segment was faulted in"
    finally:
        sys.setswitchinterval(interval)
        for t in threading.enumerate():
            if t.name == "cast-arena-9001":
                t.join(30)
        assert segment.close()


def test_nobody_can_write_a_segment_through_its_memory_file_but_the_servers_own_mapping() -> None:
    segment = Segment(1, 4 * PAGE)
    try:
        segment.view[0:5] = b"first"  # the server's mapping, made before the seals, writes
        with pytest.raises(PermissionError):
            os.pwrite(segment.fd, b"x", 0)
        with pytest.raises(PermissionError):
            mmap.mmap(segment.fd, PAGE)  # a writable shared mapping
        with pytest.raises(PermissionError):
            os.ftruncate(segment.fd, PAGE)
        # Opened again by path, read-write: the seals are the file's, not the descriptor's.
        again = os.open(f"/proc/self/fd/{segment.fd}", os.O_RDWR)
        try:
            with pytest.raises(PermissionError):
                os.pwrite(again, b"x", 0)
        finally:
            os.close(again)
        reader = mmap.mmap(segment.fd, 4 * PAGE, prot=mmap.PROT_READ)
        assert reader[0:5] == b"first"
        with pytest.raises(TypeError):
            memoryview(reader)[0:1] = b"y"
        reader.close()
    finally:
        assert segment.close()


def test_values_are_copied_in_page_aligned_and_their_extents_reused_once_nothing_holds_them() -> None:
    arena = Arena(max_bytes=64 * MIB, segment_bytes=8 * MIB)
    source = bytearray(b"a" * 100_000)
    first = arena.put(source)
    assert first is not None and first.offset % PAGE == 0 and bytes(first.view) == bytes(source)
    source[:] = b"b" * 100_000
    assert bytes(first.view) == b"a" * 100_000  # a copy: what the writer does afterwards changes nothing
    second = arena.put(b"c" * 10)
    assert second is not None and second.offset >= first.offset + 100_000
    offset = first.offset
    del first
    gc.collect()
    third = arena.put(b"d" * 5000)
    assert third is not None and third.offset == offset  # reused
    assert arena.stats()["values"] == 2


def test_a_values_largest_bytes_field_is_placed_on_a_cache_line() -> None:
    arena = Arena(max_bytes=64 * MIB, segment_bytes=8 * MIB)
    image = BytesValue(value=b"p" * 100_000).SerializeToString()  # the pixels 4 bytes in
    header = b"\x08\x2a\x12\x04rgb8"  # a varint field and a short string before them: not aligned on those
    for value in (image, header + b"\x1a\xa0\x8d\x06" + b"p" * 100_000, b"\x0a\x03abc" * 100):
        placed = arena.put(value)
        assert placed is not None and bytes(placed.view) == value
        assert (placed.offset + largest_payload(value)) % ALIGN == 0, (placed.offset, largest_payload(value))
    assert largest_payload(image) == 4 and largest_payload(header + b"\x1a\xa0\x8d\x06" + b"p" * 100_000) == 12
    small = arena.put(b"\x0a\x03abc" * 100)  # no field of LARGE bytes: at its extent's start, a page
    assert small is not None and small.offset % PAGE == 0


def test_a_lent_value_is_not_reused_until_given_back() -> None:
    arena = Arena(max_bytes=64 * MIB, segment_bytes=8 * MIB)
    placed = arena.put(b"x" * 10_000)
    assert placed is not None
    offset, value_id = placed.offset, placed.value_id
    arena.lease(placed)
    del placed
    other = arena.put(b"y" * 10_000)
    assert other is not None and other.offset != offset
    assert arena.stats()["lent_bytes"] == 10_000
    arena.give_back([value_id])
    again = arena.put(b"z" * 10_000)
    assert again is not None and again.offset == offset


def test_a_full_arena_leaves_values_as_bytes() -> None:
    shared = memory(max_bytes=64 * MIB)
    ops = [shared.place(BatchOp(Operation.ADD, "vision", f"e{i}", "t", _whole(8 * MIB))) for i in range(9)]
    placed = [op for op in ops if op.placed is not None]
    assert len(placed) == 8  # the one 64 MiB segment max_bytes allows is full
    assert isinstance(ops[-1].data, bytes) and ops[-1].placed is None
    assert shared.snapshot()["unplaced"] == 1
    assert shared.place(BatchOp(Operation.ADD, "vision", "small", "t", b"tiny")).placed is None  # under the threshold


def test_a_staged_value_is_copied_from_its_own_session_and_refusals_name_what_is_wrong() -> None:
    shared = memory()
    session = shared.open_session(WRITER)
    staging = mmap.mmap(session.staging_fd, session.staging_bytes)  # as the client maps it
    staging[0:200_000] = b"v" * 200_000
    data, placed = shared.staged(WRITER, session.id, 0, 200_000, "img")
    assert placed is not None and bytes(data) == b"v" * 200_000
    staging[0:10] = b"changed..."
    assert bytes(placed.view[0:10]) == b"v" * 10
    with pytest.raises(PermissionDeniedError, match="may not use the shared-memory session .* of component 'writer'"):
        shared.staged(OTHER, session.id, 0, 10, "img")
    with pytest.raises(InvalidArgumentError, match="outside the staging area"):
        shared.staged(WRITER, session.id, session.staging_bytes - 10, 20, "img")
    with pytest.raises(InvalidArgumentError, match="limits.max_value_bytes"):
        shared.staged(WRITER, session.id, 0, 9 * MIB, "img")
    with pytest.raises(InvalidArgumentError, match="which this server does not have"):
        shared.staged(WRITER, b"\x01" * 16, 0, 10, "img")
    staging.close()
    shared.close_session(session)
    with pytest.raises(InvalidArgumentError, match="which this server does not have"):
        shared.staged(WRITER, session.id, 0, 10, "img")  # stale: its session ended
    with pytest.raises(PermissionDeniedError):
        reader = shared.open_session(WRITER)
        shared.session_for(OTHER, reader.id)


def test_the_window_bounds_what_one_session_holds_lent_and_a_call_gives_back_what_never_arrived() -> None:
    shared = memory(window=3 * MIB)
    session = shared.open_session(WRITER)
    sent: list[int] = []
    session.send_segment = lambda segment: sent.append(segment.id) is None
    values = [shared.arena.put(_whole(MIB)) for _ in range(4)]
    lent = [shared.lend(session, 7, v) for v in values if v is not None]
    assert [x is not None for x in lent] == [True, True, True, False]  # the fourth is over the window: bytes
    assert sent == [1]  # the segment's memory file went once, before the first value in it
    assert session.lent_bytes == 3 * MIB and shared.snapshot()["over_window"] == 1
    shared.give_back(session, [999])  # a value it does not hold: ignored
    assert session.lent_bytes == 3 * MIB
    # The call ends having received only its first reference: the second and third never arrived.
    shared.received(session, 7, 1, True)
    assert session.lent_bytes == MIB  # the first, received, is held until its RELEASE
    shared.give_back(session, [lent[0].value_id, lent[0].value_id])  # type: ignore[union-attr]  # once is all
    assert session.lent_bytes == 0 and shared.snapshot()["lent_bytes"] == 0


def test_one_emptied_segment_is_kept_as_a_spare_while_values_come_and_retired_once_they_stop() -> None:
    """The next segment the values need is the spare, whose pages are faulted in: no new memory file is made."""
    arena = Arena(max_bytes=64 * MIB, segment_bytes=8 * MIB)
    first = [arena.put(_whole(2 * MIB)) for _ in range(4)]  # segment 1, full
    second = [arena.put(_whole(2 * MIB)) for _ in range(4)]  # segment 2, full
    third = [arena.put(_whole(2 * MIB))]  # segment 3
    assert third[0] is not None and third[0].segment == 3 and arena.stats()["segments"] == 3
    del first, second, third[0]  # segments 1 and 2 emptied (the history moved on); 3 is empty too
    gc.collect()
    third = [arena.put(_whole(2 * MIB))]  # values still come: into segment 1, the first with room
    assert third[0] is not None and third[0].segment == 1
    assert arena.retire_empty() == [3]  # 2 stays as the spare, 3 goes: at most one spare
    assert arena.stats()["segments"] == 2
    third += [arena.put(_whole(2 * MIB)) for _ in range(4)]  # segment 1 full: the fourth goes to the spare
    assert third[-1] is not None and third[-1].segment == 2  # not a new memory file with fresh pages
    del third[-1]
    gc.collect()
    now = time.monotonic()
    assert arena.retire_empty(now) == []  # values came just now: 2 stays as the spare
    assert arena.retire_empty(now + SPARE_IDLE_S) == [2]  # none came for a while: the writers stopped, it goes
    assert arena.stats()["segments"] == 1 and arena.stats()["segment_bytes"] == 8 * MIB
    arena.close()


def test_an_ended_session_gives_back_everything_and_empty_segments_are_retired() -> None:
    shared = SharedMemory(SharedSettings(True, 1, 256 * MIB, 256 * MIB), Limits(max_value_bytes=8 * MIB))
    session = shared.open_session(WRITER)
    session.send_segment = lambda segment: True
    values = [shared.arena.put(_whole(8 * MIB)) for _ in range(9)]  # two segments of 64 MiB
    assert shared.snapshot()["segments"] == 2
    for v in values:
        assert v is not None and shared.lend(session, 1, v) is not None
    del values, v
    gc.collect()
    assert shared.snapshot()["values"] == 9  # lent: held
    shared.close_session(session)
    assert shared.snapshot()["values"] == 0 and shared.snapshot()["sessions"] == 0
    assert shared.retire_empty() == [2]  # the first stays for the next value
    assert shared.snapshot()["segments"] == 1
    shared.close()
