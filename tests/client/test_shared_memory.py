"""Large values by shared memory on one host (docs/client-protocol.md, "Large values by shared memory").

A real server on port 0 (in a thread of this process, which is on its host)
with shared memory on; components over gRPC. The raw protocol (a session's
frames, requests built by hand) plays the writer or reader that misbehaves.
"""

from __future__ import annotations

import logging
import mmap
import os
import socket
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy
import pytest
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client import shm, shm_session
from cast.core import arena
from cast.core.records import Limits
from cast.core.shared import SharedSettings
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import inspection_pb2_grpc as insp_grpc
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire import shared_memory as wire
from tests.client.shm_host import BYTES_VALUE, MIB, Host, image
from tests.client.shm_host import host as host  # the fixture, used by name
from tests.conftest import wait_for


def staged_add(session: shm_session.ClientSession, entry_id: str, value: BytesValue) -> wm_pb2.AddRequest:
    """An Add whose value a raw client staged in its session."""
    data = value.SerializeToString()
    staged = session.stage(data)
    assert staged is not None
    request = wm_pb2.AddRequest()
    request.address.id, request.address.subarchitecture = entry_id, "vision"
    request.value.type_url = "type.googleapis.com/" + BYTES_VALUE
    request.staged_value.CopyFrom(session.staged_value(staged))
    return request


def test_large_values_go_by_reference_to_readers_on_the_host_and_read_back_identical(host: Any) -> None:
    h = host()
    writer, reader = h.component("writer"), h.component("reader")
    seen: list[tuple[int, bytes, bool]] = []
    reader.on_change(cast.address_filter("img", include_entry=True),
                     lambda ch: seen.append((ch.revision, ch.entry(BytesValue).value.value, ch.view().shared)))
    frames = [image(MIB, seed) for seed in range(3)]
    writer.add("img", frames[0])
    writer.overwrite("img", frames[1])
    writer.overwrite("img", frames[2])
    writer.add("small", BytesValue(value=b"tiny"))
    wait_for(lambda: len(seen) == 3, what="three events")
    assert seen == [(i + 1, frames[i].value, True) for i in range(3)]
    assert reader.get("img", BytesValue) == frames[2]
    assert [e.value for e in reader.get_all(BytesValue)] == [BytesValue(value=b"tiny"), frames[2]]
    with reader.get_view("img") as view:
        assert view.shared and view.type == BYTES_VALUE and view.version == writer.get_entry("img", BytesValue).version
        assert bytes(view.field(1)) == frames[2].value  # the pixels, not copied
        assert view.decode(BytesValue) == frames[2]
    with reader.get_view("small") as view:
        assert not view.shared and bytes(view.data) == BytesValue(value=b"tiny").SerializeToString()
    stats = h.shared()
    assert stats["staged_writes"] == 3 and stats["lent"] >= 5 and stats["sessions"] == 2
    wait_for(lambda: h.shared()["lent_bytes"] == 0, what="every lent value given back")


class _CountingSocket:
    """A session's socket that counts the reads made of it."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.reads = 0

    def recvmsg(self, *args: Any) -> Any:
        self.reads += 1
        return self._sock.recvmsg(*args)

    def recvmsg_into(self, *args: Any) -> Any:
        self.reads += 1
        return self._sock.recvmsg_into(*args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


def test_the_socket_reads_go_into_one_buffer_kept_from_read_to_read() -> None:
    """A fresh 256 KiB bytes object per read was an mmap and a munmap each time."""
    inbox = wire.Inbox(1024)
    ours, theirs = socket.socketpair()
    with ours, theirs:
        seen = []
        for n in range(3):
            fd = os.memfd_create("t")
            try:
                wire.send(theirs, wire.segment(n, 4096), fd)
                data, fds = inbox.receive(ours)
            finally:
                os.close(fd)
            [frame] = wire.FrameReader().feed(data, fds)
            assert (frame.kind, wire.parse_segment(frame.body)) == (wire.SEGMENT, (n, 4096))
            assert frame.fd is not None and os.fstat(frame.fd).st_size == 0
            os.close(frame.fd)
            assert len(data) < inbox.size  # a short read: the socket held no more
            seen.append(data.obj)
        assert seen[0] is seen[1] is seen[2]


def test_a_bad_frame_leaves_every_memory_file_of_its_read_to_close() -> None:
    """Frames cut before a bad one in the same read are not handed out: their files go to stray(), none is lost."""
    reader = wire.FrameReader()
    fds = [os.memfd_create("t") for _ in range(3)]
    good = wire.segment(1, 4096) + wire.segment(2, 4096)
    with pytest.raises(wire.ProtocolError, match="1 to"):
        reader.feed(good + b"\x00\x00\x00\x00\x04", fds)  # two SEGMENT frames, then a length of 0
    assert sorted(reader.stray()) == sorted(fds)
    for fd in fds:
        os.close(fd)


def test_a_watcher_reads_each_events_frame_with_one_read_of_its_socket(host: Any) -> None:
    """A read that brings less than the buffer holds emptied the socket: no second read just to learn it."""
    h = host()
    writer, reader = h.component("writer"), h.component("reader")
    seen: list[int] = []
    reader.on_change(cast.address_filter("img", include_entry=True), lambda ch: seen.append(ch.revision))
    writer.add("img", image(MIB, 0))  # its segment comes before the first reference
    wait_for(lambda: len(seen) == 1, what="the first event")
    session = reader._transport._directory.shared.session()
    counting = _CountingSocket(session._sock)
    session._sock = counting
    receiver = session._receiver  # the compiled build reads in C, and counts its reads itself
    before = receiver.reads if receiver is not None else 0
    for n in range(1, 6):
        writer.overwrite("img", image(MIB, n))
        wait_for(lambda n=n: len(seen) == n + 1, what=f"event {n + 1}")  # type: ignore[misc]
    reads = counting.reads if receiver is None else receiver.reads - before
    assert reads == 5, reads


def test_a_lent_image_starts_on_a_cache_line_so_arrays_over_it_are_aligned(host: Any) -> None:
    """numpy's aligned flag on a view of the pixels: unaligned, its ufuncs take a buffered path (twice the time)."""
    h = host()
    writer, reader = h.component("writer"), h.component("reader")
    for size in (64 << 10, MIB, 6 * MIB + 40):  # a 2-, 3- and 4-byte length before the pixels
        writer.add(f"img{size}", BytesValue(value=bytes(size)))
        with reader.get_view(f"img{size}") as view:
            pixels = view.field(1)
            assert view.shared and len(pixels) == size
            words = numpy.frombuffer(pixels, dtype=numpy.float64, count=size // 8)
            assert words.flags.aligned and words.ctypes.data % arena.ALIGN == 0, (size, words.ctypes.data % 64)
            del words, pixels


def test_a_writer_cannot_change_a_value_after_its_write_was_acknowledged(
    host: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    passed: list[int] = []  # the memory files of the segments, as they reach a client
    segment_init = shm_session._Segment.__init__

    def keep(segment: Any, fd: int, size: int) -> None:
        passed.append(os.dup(fd))
        segment_init(segment, fd, size)

    monkeypatch.setattr(shm_session._Segment, "__init__", keep)
    h = host()
    reader = h.component("reader")
    seen: list[bytes] = []
    reader.on_change(cast.address_filter("img", include_entry=True),
                     lambda ch: seen.append(bytes(ch.view().field(1))))
    session = h.session("writer")
    original = image(MIB)
    request = staged_add(session, "img", original)
    h.stub().Add(request, metadata=h.metadata("writer"))  # acknowledged
    staging = session._staging_view  # the writer still has its staging area mapped, writable
    staging[0: MIB] = b"\xff" * MIB
    wait_for(lambda: seen, what="the event")
    assert seen == [original.value] and reader.get("img", BytesValue) == original
    # The value now lives in the server's memory file; the writer gets it lent like any reader and cannot write it.
    call = session.new_call()
    entry = h.stub().Get(wm_pb2.GetRequest(address={"id": "img", "subarchitecture": "vision"}),
                         metadata=h.metadata("writer") + call.metadata).entry
    assert entry.HasField("shared_value") and not entry.value.value
    session.poll(wait=1.0)
    assert passed
    # The memory file as it was passed (opened read-write), and opened again by its path, read-write.
    again = os.open(f"/proc/self/fd/{passed[-1]}", os.O_RDWR)
    try:
        for fd in (passed[-1], again):
            with pytest.raises(PermissionError):
                os.pwrite(fd, b"\x00", entry.shared_value.offset)
            with pytest.raises(PermissionError):
                mmap.mmap(fd, 4096, offset=entry.shared_value.offset - entry.shared_value.offset % 4096)
            with pytest.raises(PermissionError):
                os.ftruncate(fd, 0)
    finally:
        for fd in (again, *passed):
            os.close(fd)
    call.end()
    assert reader.get("img", BytesValue) == original
    session.close()


def test_a_reader_cannot_write_what_it_was_lent(host: Any) -> None:
    h = host()
    writer, reader = h.component("writer"), h.component("reader")
    writer.add("img", image(MIB))
    with reader.get_view("img") as view:
        assert view.shared
        data = view.data
        with pytest.raises(TypeError):
            data[0:1] = b"x"  # read-only
        with pytest.raises(TypeError):
            view.field(1)[0:1] = b"x"
        del data
    assert reader.get("img", BytesValue) == image(MIB)


def test_forged_and_stale_references_are_refused_with_a_clear_error_and_change_nothing(host: Any) -> None:
    h = host()
    writer = h.component("writer")
    writer.add("img", image(MIB))
    before = writer.get_entry("img", BytesValue)
    stub = h.stub()
    session = h.session("writer")
    good = staged_add(session, "img", image(MIB, 7))

    def overwrite(change: Callable[[wm_pb2.OverwriteRequest], None], who: str = "writer") -> grpc.RpcError:
        request = wm_pb2.OverwriteRequest(address=good.address, value=good.value, staged_value=good.staged_value)
        change(request)
        with pytest.raises(grpc.RpcError) as refused:
            stub.Overwrite(request, metadata=h.metadata(who))
        return refused.value

    def forged(r: wm_pb2.OverwriteRequest) -> None:
        r.staged_value.session = b"\x07" * 16

    def outside(r: wm_pb2.OverwriteRequest) -> None:
        r.staged_value.offset = session._regions.size - 10

    def both(r: wm_pb2.OverwriteRequest) -> None:
        r.value.value = b"\x0a\x01x"

    def over(r: wm_pb2.OverwriteRequest) -> None:
        r.staged_value.size = 9 * MIB

    cases = [(forged, "writer", grpc.StatusCode.INVALID_ARGUMENT, "which this server does not have"),
             (outside, "writer", grpc.StatusCode.INVALID_ARGUMENT, "outside the staging area"),
             (both, "writer", grpc.StatusCode.INVALID_ARGUMENT, "has both bytes"),
             (over, "writer", grpc.StatusCode.INVALID_ARGUMENT, "limits.max_value_bytes"),
             (lambda r: None, "other", grpc.StatusCode.PERMISSION_DENIED, "may not use the shared-memory session")]
    for change, who, code, words in cases:
        error = overwrite(change, who)
        assert error.code() == code and words in (error.details() or ""), error.details()
    session.close()
    wait_for(lambda: h.shared()["sessions"] == 1, what="the raw session's end")
    stale = overwrite(lambda r: None)  # its session ended
    assert stale.code() == grpc.StatusCode.INVALID_ARGUMENT and "which this server does not have" in stale.details()
    for bad, code in (("nothex/1", grpc.StatusCode.INVALID_ARGUMENT),
                      (f"{writer._transport._directory.shared.session().id.hex()}/1",
                       grpc.StatusCode.PERMISSION_DENIED)):  # another component's session
        with pytest.raises(grpc.RpcError) as refused:
            stub.Get(wm_pb2.GetRequest(address=good.address),
                     metadata=h.metadata("other") + (("cast-shared-memory", bad),))
        assert refused.value.code() == code
    after = writer.get_entry("img", BytesValue)
    assert (after.version, after.revision, after.value) == (before.version, before.revision, before.value)


def test_the_rules_are_the_same_for_values_in_shared_memory(host: Any) -> None:
    h = host()
    writer, other = h.component("writer"), h.component("other")
    seer = h.component("seer", "language")
    latest: list[tuple[int, int]] = []
    gate = threading.Event()

    def slow(ch: cast.WorkingMemoryChange) -> None:
        gate.wait(10)
        latest.append((ch.entry(BytesValue).value.value[0], ch.skipped))

    seer.on_change(cast.address_filter("img", subarchitecture="vision", include_entry=True), slow, delivery="latest")
    first = writer.add("img", image(MIB, 0))
    with pytest.raises(cast.ConsistencyError):
        writer.overwrite("img", image(MIB, 1), expected_version=first.version + 5)
    with other.lock("img", cast.LockMode.O):
        with pytest.raises(cast.LockedError, match="locked .* by component 'other'"):
            writer.overwrite("img", image(MIB, 2))
    with pytest.raises(cast.PermissionDeniedError):
        seer.overwrite("img", image(MIB, 3), subarchitecture="vision")
    assert writer.get("img", BytesValue) == image(MIB, 0)
    for seed in range(1, 6):
        writer.overwrite("img", image(MIB, seed))
    gate.set()
    wait_for(lambda: latest and latest[-1][0] == 5, what="the newest value")
    assert sum(skipped for _, skipped in latest) + len(latest) == 6  # the add and five overwrites, none lost
    wait_for(lambda: h.shared()["lent_bytes"] == 0, what="every lent value given back")
    # The refused writes' copies are gone: the arena holds the entry and the history's values only.
    assert h.shared()["values"] == 6


def test_views_hold_their_value_past_the_history_and_the_window_sends_the_rest_as_bytes(host: Any) -> None:
    h = host(settings=SharedSettings(window_bytes=3 * MIB + 64), limits=Limits(history_bytes=2 * MIB))
    writer, reader = h.component("writer"), h.component("reader")
    writer.add("img", image(MIB, 0))
    views = [reader.get_view("img")]
    for seed in range(1, 4):
        writer.overwrite("img", image(MIB, seed))
        views.append(reader.get_view("img"))
    # Three lent (the window), the fourth as bytes; each still reads the value of its version.
    assert [v.shared for v in views] == [True, True, True, False]
    assert [bytes(v.field(1)) for v in views] == [image(MIB, seed).value for seed in range(4)]
    assert h.shared()["over_window"] == 1
    for v in views:
        v.release()
    with pytest.raises(cast.InvalidArgumentError, match="released"):
        views[0].field(1)
    wait_for(lambda: h.shared()["lent_bytes"] == 0, what="the views' values given back")
    assert h.shared()["values"] <= 3  # the entry's and what the 2 MiB history keeps


def test_a_client_told_it_is_on_another_host_gets_identical_values_as_bytes(
    host: Any, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    h = host()
    writer, reader = h.component("writer"), h.component("reader")
    monkeypatch.setenv(shm.ENV, "off")
    caplog.set_level(logging.INFO, logger="cast.client")
    remote = h.component("remote")
    got: list[bytes] = []
    remote.on_change(cast.address_filter("img", include_entry=True), lambda ch: got.append(ch.entry(BytesValue)
                                                                                           .value.value))
    remote.add("from-remote", image(MIB, 9))
    writer.add("img", image(MIB, 1))
    wait_for(lambda: got, what="the event")
    assert got == [image(MIB, 1).value]
    with remote.get_view("img") as view:
        assert not view.shared and bytes(view.field(1)) == image(MIB, 1).value
    assert reader.get("from-remote", BytesValue) == image(MIB, 9)
    said = [r.getMessage() for r in caplog.records if "is not used" in r.getMessage()]
    assert len(said) == 1 and f"turned off by {shm.ENV}=off" in said[0]
    # The remote one's write came as bytes; the server still keeps it in shared memory for the host's readers.
    stats = h.shared()
    assert stats["staged_writes"] == 1 and stats["values"] == 2


def test_memory_stays_bounded_with_a_slow_queue_watcher_and_with_latest(host: Any) -> None:
    window = 4 * MIB
    history = 6 * MIB
    h = host(settings=SharedSettings(window_bytes=window), limits=Limits(history_bytes=history))
    writer = h.component("writer")
    slow_queue, slow_latest = h.component("q"), h.component("l")
    gate = threading.Event()
    got: dict[str, list[int]] = {"queue": [], "latest": []}

    def reader(name: str) -> Callable[[cast.WorkingMemoryChange], None]:
        def take(ch: cast.WorkingMemoryChange) -> None:
            # Held until every write was made (set on failure too): a loaded machine may take a minute or more.
            gate.wait(600)
            got[name].append(ch.entry(BytesValue).value.value[0])
        return take

    slow_queue.on_change(cast.address_filter("img", include_entry=True), reader("queue"))
    slow_latest.on_change(cast.address_filter("img", include_entry=True), reader("latest"), delivery="latest")
    # And a raw watcher that never reads its stream at all: what it was lent stays lent.
    session = h.session("stalled")
    call = session.new_call()
    created = threading.Event()

    def requests() -> Iterator[wm_pb2.WatchRequest]:
        yield wm_pb2.WatchRequest(create=wm_pb2.WatchCreate(watch_id=1, filters=[
            {"id": "img", "subarchitecture": "vision", "include_entry": True}]))
        created.wait(30)

    stalled = h.stub().Watch(requests(), metadata=h.metadata("stalled") + call.metadata)
    next(stalled)  # WatchCreated; nothing more is read
    writer.add("img", image(MIB, 0))
    peak = 0
    try:
        for seed in range(1, 60):
            writer.overwrite("img", image(MIB, seed))
            peak = max(peak, h.shared()["value_bytes"])
            # The queue watcher's client has taken it (its standby thread reads while the first callback blocks):
            # without this wait a loaded machine could let the writer outrun that thread, and the watch fall
            # behind the short history on the server, as designed for a reader that does not keep up.
            wait_for(lambda n=seed + 1: slow_queue._dispatcher._pending == n, what=f"value {seed} queued in the client")
    finally:
        gate.set()
    # History, the entry, and what each of the three readers may hold lent: never more, however far behind.
    bound = history + MIB + 3 * (window + MIB)
    assert peak <= bound, f"{peak} bytes held, over {bound}"
    wait_for(lambda: got["latest"] and got["latest"][-1] == 59 % 251, what="latest's newest value")
    wait_for(lambda: len(got["queue"]) == 60, what="every value to the queue watcher")
    assert got["queue"] == [seed % 251 for seed in range(60)]  # in order, none lost
    created.set()
    stalled.cancel()
    session.close()
    wait_for(lambda: h.shared()["lent_bytes"] == 0, what="every lent value given back")
    # The cancelled stream's task lets go of the values it had queued when it ends, which may come after
    # its session gave back its leases: the history's values and the entry's are what stays, in the end.
    wait_for(lambda: h.shared()["value_bytes"] <= history + MIB,
             what=f"no more than the history and the entry's value held ({history + MIB} bytes)")


def test_values_in_shared_memory_are_durable_with_the_journal(tmp_path: Path) -> None:
    h = Host(tmp_path, journal=True)
    try:
        writer = h.component("writer")
        writer.add("img", image(2 * MIB, 3))
        assert h.shared()["staged_writes"] == 1
    finally:
        h.close()
    again = Host(tmp_path, journal=True)
    try:
        reader = again.component("reader")
        assert reader.get("img", BytesValue) == image(2 * MIB, 3)
    finally:
        again.close()


def test_the_tools_show_shared_memory_and_one_setting_turns_it_off(host: Any) -> None:
    h = host()
    writer = h.component("writer")
    writer.add("img", image(MIB))
    inspection = insp_grpc.InspectionStub(h.channel)
    listing = inspection.ListEntries(insp_pb2.ListEntriesRequest(subarchitecture="vision"), metadata=h.metadata("t"))
    assert listing.shared_bytes == len(image(MIB).SerializeToString())
    metrics = inspection.GetMetrics(insp_pb2.GetMetricsRequest(), metadata=h.metadata("t"))
    assert metrics.shared_memory.staged_writes == 1 and metrics.shared_memory.segments == 1
    off = host(settings=SharedSettings(enabled=False))
    desc = dir_grpc.DirectoryStub(off.channel).DescribeSystem(dir_pb2.DescribeSystemRequest(),
                                                               metadata=off.metadata("t"))
    assert not desc.HasField("shared_memory")
    assert not inspection_of(off).GetMetrics(insp_pb2.GetMetricsRequest(), metadata=off.metadata("t")).HasField(
        "shared_memory")
    c = off.component("c")
    c.add("img", image(MIB))
    with c.get_view("img") as view:
        assert not view.shared and bytes(view.field(1)) == image(MIB).value


def inspection_of(h: Host) -> insp_grpc.InspectionStub:
    return insp_grpc.InspectionStub(h.channel)


def test_the_configuration_sets_shared_memory_and_refuses_what_is_wrong(tmp_path: Path) -> None:
    from cast.config import ConfigError, load_config

    path = tmp_path / "system.yaml"
    path.write_text("subarchitectures: {vision: {}}\nshared_memory: {threshold_bytes: 1000, window_bytes: 4096}\n")
    assert load_config(path, environ={}).shared_memory == SharedSettings(True, 1000, 1 << 30, 4096)
    path.write_text("subarchitectures: {vision: {}}\nshared_memory: {enabled: false}\n")
    assert not load_config(path, environ={}).shared_memory.enabled
    assert load_config(path, environ={}).shared_memory == SharedSettings(enabled=False)
    path.write_text("subarchitectures: {vision: {}}\nshared_memory: {enable: false, threshold_bytes: 0}\n")
    with pytest.raises(ConfigError) as refused:
        load_config(path, environ={})
    text = str(refused.value)
    assert "shared_memory.enable" in text and "did you mean 'enabled'" in text and "threshold_bytes" in text
