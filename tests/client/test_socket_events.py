"""A watch's events on the session's socket (docs/client-protocol.md, "A watch's events on the session's socket").

A real server on port 0 with shared memory on (tests/client/test_shared_memory.py's
``Host``); a Python component's watch asks for its event batches as EVENTS
frames on its session's socket, which its dispatcher thread reads itself. The
raw protocol plays the client that asks and then does not read.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import grpc
import pytest
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client import shm_session
from cast.client.local_transport import LocalTransport
from cast.client.watch_stream import EVENTS_METADATA, WatchStream
from cast.core.records import Identity, Limits
from cast.core.shared import SharedSettings
from cast.errors import UnavailableError
from cast.server.socket_writes import MAX_UNSENT
from cast.server.working_memory import EVENTS_UNSENT
from cast.v1 import working_memory_pb2 as wm_pb2
from tests.client.shm_host import MIB, Host, image
from tests.client.shm_host import host as host  # the fixture, used by name
from tests.conftest import wait_for


def _seeds(got: list[int]) -> Callable[[cast.WorkingMemoryChange], None]:
    def take(change: cast.WorkingMemoryChange) -> None:
        if change.operation is not cast.Operation.DELETE:
            with change.view() as view:
                got.append(view.field(1)[0])
    return take


def _every_value_watched(h: Host, count: int) -> Any:
    """A writer adds "img" and overwrites it to ``count`` values of a MiB; a watcher gets each once, in order.

    The watcher component, for what a test checks after.
    """
    writer, watcher = h.component("writer"), h.component("watcher")
    got: list[int] = []
    watcher.on_change(cast.address_filter("img", include_entry=True), _seeds(got))
    writer.add("img", image(MIB, 0))
    for seed in range(1, count):
        writer.overwrite("img", image(MIB, seed))
    wait_for(lambda: len(got) == count, what="every value")
    assert got == [seed % 251 for seed in range(count)]  # in order, each once
    return watcher


def _raw_watch(h: Host, cid: str, session: shm_session.ClientSession, on_socket: bool,
               stop: threading.Event, latest: bool = False) -> tuple[Any, shm_session.ReadCall]:
    """A Watch call of a raw client on ``session`` for "img", its events asked on the socket or not."""
    call = session.new_call()

    def requests() -> Any:
        yield wm_pb2.WatchRequest(create=wm_pb2.WatchCreate(watch_id=1, filters=[
            {"id": "img", "subarchitecture": "vision", "include_entry": True}],
            delivery=wm_pb2.DELIVERY_LATEST if latest else wm_pb2.DELIVERY_QUEUE))
        stop.wait(30)

    metadata = h.metadata(cid) + call.metadata + ((EVENTS_METADATA,) if on_socket else ())
    stream = h.stub().Watch(requests(), metadata=metadata)
    assert next(stream).HasField("created")
    return stream, call


def _spy_on_event_frames(monkeypatch: pytest.MonkeyPatch, threads: list[str]) -> None:
    """Note in ``threads`` the thread that hands each EVENTS frame to its watch call (whichever path reads it)."""
    original = WatchStream._handler

    def spy(self: WatchStream, read: shm_session.ReadCall) -> Callable[[bytes], None]:
        handler = original(self, read)

        def noted(body: bytes) -> None:
            threads.append(threading.current_thread().name)
            handler(body)

        return noted

    monkeypatch.setattr(WatchStream, "_handler", spy)


def test_a_components_events_come_as_frames_read_by_its_dispatcher_thread(
    host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch
) -> None:
    events: list[str] = []
    _spy_on_event_frames(monkeypatch, events)
    h = host()
    _every_value_watched(h, 20)
    assert len(events) >= 1 and set(events) == {"cast-dispatch-watcher"}, events


def test_the_server_sends_a_calls_events_on_the_socket_only_when_the_call_asks(host: Callable[..., Host]) -> None:
    h = host()
    stop = threading.Event()
    asked, plain = h.session("asked"), h.session("plain")
    frames: list[bytes] = []
    stream, call = _raw_watch(h, "asked", asked, True, stop)
    asked.event_handlers[call.number] = frames.append
    other, _ = _raw_watch(h, "plain", plain, False, stop)
    writer = h.component("writer")
    writer.add("img", image(MIB, 7))
    wait_for(lambda: (asked.poll(0.05), frames)[1], what="an EVENTS frame")
    (event,) = wm_pb2.WatchResponse.FromString(frames[0]).events
    assert event.entry.address.id == "img" and event.entry.HasField("shared_value")  # lent, by reference
    response = next(other)  # the call that did not ask gets its events on the call
    assert [e.entry.address.id for e in response.events] == ["img"]
    stop.set()
    stream.cancel()
    other.cancel()
    asked.close()
    plain.close()


def test_a_watch_whose_socket_ends_resumes_on_a_new_one_without_gap_or_duplicate(host: Callable[..., Host]) -> None:
    h = host()
    writer, watcher = h.component("writer"), h.component("watcher")
    got: list[int] = []
    watcher.on_change(cast.address_filter("img", include_entry=True), _seeds(got))
    writer.add("img", image(MIB, 0))
    for seed in range(1, 10):
        writer.overwrite("img", image(MIB, seed))
    wait_for(lambda: len(got) == 10, what="the first values")
    shared = h.system.shared
    assert shared is not None
    link = h.link("watcher")
    h.server.loop.call_soon_threadsafe(link.close, "ended by the test")  # type: ignore[attr-defined]
    for seed in range(10, 40):
        writer.overwrite("img", image(MIB, seed))
    wait_for(lambda: len(got) == 40, what="every value after the socket ended")
    assert got == [seed % 251 for seed in range(40)]  # in order, each once
    stream = watcher._transport._directory.watch_stream
    assert stream.reconnects >= 1  # the call ended with its socket and was opened again
    wait_for(lambda: [s for s in shared.sessions.values() if s.who.component_id == "watcher"],
             what="the watcher's new session")


def test_a_client_that_does_not_read_its_socket_holds_up_nothing_and_its_frames_stay_bounded(
    host: Callable[..., Host]
) -> None:
    h = host(settings=SharedSettings(window_bytes=4 * MIB))
    stop = threading.Event()
    stalled = h.session("stalled")
    stream, _ = _raw_watch(h, "stalled", stalled, True, stop)  # its socket is never read
    _every_value_watched(h, 40)  # past the stalled one's window of lent values: bytes in its frames
    link = h.link("stalled")
    # What waits for the client: the bound, then at most one batch (here one value of 1 MiB and its event).
    assert link.unsent <= EVENTS_UNSENT + 2 * MIB, link.unsent
    stop.set()
    stream.cancel()
    stalled.close()


def test_a_latest_watch_whose_client_does_not_read_its_socket_keeps_the_newest_value_not_its_place(
    host: Callable[..., Host]
) -> None:
    """The server holds the newest change for it while its frames wait, so it never falls behind the history."""
    h = host(limits=Limits(history_events=16), settings=SharedSettings(window_bytes=4 * MIB))  # then bytes
    stop = threading.Event()
    stalled = h.session("stalled")
    frames: list[bytes] = []
    stream, call = _raw_watch(h, "stalled", stalled, True, stop, latest=True)
    writer = h.component("writer")
    writer.add("img", image(MIB, 0))
    for seed in range(1, 60):  # the first few fill what may wait unsent; the rest pass the history by far
        writer.overwrite("img", image(MIB, seed))
    stalled.event_handlers[call.number] = frames.append
    got: list[tuple[int, int]] = []  # revision, skipped
    deadline = time.monotonic() + 30
    while (not got or got[-1][0] < 60) and time.monotonic() < deadline:
        stalled.poll(0.05)
        got = [(e.revision, e.skipped) for f in frames for e in wm_pb2.WatchResponse.FromString(f).events]
    assert got and got[-1][0] == 60, got  # the newest value came, and the call did not end
    assert sum(1 + skipped for _, skipped in got) == 60 and len(got) < 60, got
    stop.set()
    stream.cancel()
    stalled.close()


def test_values_under_the_threshold_come_in_the_frames_as_bytes(host: Callable[..., Host]) -> None:
    h = host()
    writer, watcher = h.component("writer"), h.component("watcher")
    got: list[bytes] = []
    done = threading.Event()

    def take(change: cast.WorkingMemoryChange) -> None:
        got.append(change.entry(BytesValue).value.value)
        if len(got) == 3:
            done.set()

    watcher.on_change(cast.address_filter("small", include_entry=True), take)
    writer.add("small", BytesValue(value=b"a"))
    writer.overwrite("small", BytesValue(value=b"b"))
    writer.overwrite("small", BytesValue(value=b"c"))
    assert done.wait(10)
    assert got == [b"a", b"b", b"c"]


def test_frames_another_thread_reads_reach_the_callbacks_in_order_once(
    host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch
) -> None:
    # A read waiting for its segment reads the session's socket on its own thread, EVENTS frames included:
    # those are queued for the dispatcher behind the frames before them, never delivered out of order.
    readers: list[str] = []
    _spy_on_event_frames(monkeypatch, readers)
    h = host()
    writer, watcher = h.component("writer"), h.component("watcher")
    got: list[int] = []
    seeds = _seeds(got)

    def slow(change: cast.WorkingMemoryChange) -> None:
        time.sleep(0.002)  # the socket waits meanwhile, for the other thread to read
        seeds(change)

    watcher.on_change(cast.address_filter("img", include_entry=True), slow)
    session = watcher._transport._directory.shared.session()
    done = threading.Event()

    def other_reader() -> None:
        while not done.is_set():
            session.poll(0.001)

    thread = threading.Thread(target=other_reader, name="other-reader")
    thread.start()
    try:
        writer.add("img", image(MIB, 0))
        for seed in range(1, 60):
            writer.overwrite("img", image(MIB, seed))
        wait_for(lambda: len(got) == 60, what="every value")
    finally:
        done.set()
        thread.join()
    assert got == [seed % 251 for seed in range(60)]  # in order, each once
    assert "other-reader" in readers  # the path this test is for was taken


def test_a_value_that_cannot_be_claimed_reopens_the_call_without_gap_or_duplicate(
    host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch
) -> None:
    original = shm_session.ClientSession.claim_at
    claims = [0]

    def fails_once(self: shm_session.ClientSession, *ref: int) -> Any:
        claims[0] += 1
        if claims[0] == 5:
            raise UnavailableError("shared-memory segment 99 did not arrive (a test): read again")
        return original(self, *ref)

    monkeypatch.setattr(shm_session.ClientSession, "claim_at", fails_once)
    # Every claim through the session's claim_at, where the failure is put: the C claimer calls it only for what
    # it does not do itself (tests/client/test_native_leases.py holds the two to the same answers and errors).
    monkeypatch.setattr(shm_session.ReadCall, "claimer", lambda self: self.claim_at)
    h = host()
    watcher = _every_value_watched(h, 20)  # the frame that failed and those behind it came again, each once
    assert claims[0] > 20 and watcher._transport._directory.watch_stream.reconnects >= 1


@pytest.mark.parametrize("journal", [False, True], ids=["memory", "journal"])
def test_writes_made_on_other_threads_reach_every_socket_watcher_once_in_order(
    host: Callable[..., Host], journal: bool
) -> None:
    # An in-process component writes on its own thread; with a journal that defers, writes become visible on
    # the journal's committer thread: either way the wake-up comes from a thread other than the server's loop.
    h = host(journal=journal)
    seen: list[list[bytes]] = []
    for n in range(3):
        got: list[bytes] = []
        seen.append(got)
        h.component(f"watcher{n}").on_change(cast.address_filter("e", include_entry=True),
                                             lambda ch, got=got: got.append(ch.entry(BytesValue).value.value))
    identity = Identity("in-process", "vision")
    local = cast.UnmanagedComponent()
    local._cast_bind(LocalTransport(h.system, identity))
    try:
        local.add("e", BytesValue(value=b"0"))
        for n in range(1, 20):
            local.overwrite("e", BytesValue(value=str(n).encode()))
        wait_for(lambda: all(len(got) == 20 for got in seen), what="every watcher's events")
        assert seen == [[str(n).encode() for n in range(20)]] * 3  # each value once, in order, to every watcher
    finally:
        local._cast_close()


def test_a_socket_watch_that_fell_behind_the_history_ends_with_out_of_range_once_its_client_reads(
    host: Callable[..., Host]
) -> None:
    h = host(settings=SharedSettings(window_bytes=4 * MIB), limits=Limits(history_events=8))
    stop = threading.Event()
    stalled = h.session("stalled")
    stream, call = _raw_watch(h, "stalled", stalled, True, stop)  # its socket is not read for now
    stalled.event_handlers[call.number] = lambda body: None
    try:
        writer = h.component("writer")
        writer.add("img", image(MIB, 0))
        for seed in range(1, 40):  # past the 4 MiB the server sends it unread, then past the history (8 events)
            writer.overwrite("img", image(MIB, seed))
        assert not stream.done()  # a client that does not read lags on the server: its call stays open
        wait_for(lambda: (stalled.poll(0.05), stream.done())[1], what="the watch's end once its client read")
        assert stream.code() == grpc.StatusCode.OUT_OF_RANGE, stream.details()
        assert "history" in (stream.details() or "")
    finally:
        stop.set()
        stream.cancel()
        stalled.close()


def test_a_watcher_whose_queue_is_full_gives_back_its_values_and_keeps_its_session(host: Callable[..., Host]) -> None:
    # A component whose callbacks are slower than the writer fills its queue and stops reading its socket, so
    # more than MAX_UNSENT waits for it on the server; meanwhile each callback gives back its value (a RELEASE
    # sent from the dispatcher thread). The server reads those on (it holds only the client's writes), so no
    # RELEASE waits on a full socket and the session, and the watch on it, live on: every value comes, in order.
    h = host(limits=Limits(history_events=10_000))
    writer, watcher = h.component("writer"), h.component("watcher")
    watcher._dispatcher.capacity = 20
    count, got = 2_000, []
    take = _seeds(got)

    def slow(change: cast.WorkingMemoryChange) -> None:
        take(change)
        time.sleep(0.001)

    watcher.on_change(cast.address_filter("img", include_entry=True), slow)
    session = watcher._transport._directory.shared.session()
    link = h.link("watcher")
    most = [0]  # the most that waited for the watcher, sampled (a spy would not see into the compiled build)
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.0005):
            most[0] = max(most[0], link.unsent)

    sampler = threading.Thread(target=sample)
    sampler.start()
    try:
        writer.add("img", image(64 << 10, 0))
        # Pipelined, so that the writer outruns the watcher by far more than MAX_UNSENT on a loaded machine too.
        written = [writer.overwrite_async("img", image(64 << 10, seed)) for seed in range(1, count)]
        for w in written:
            w.result(60)
        wait_for(lambda: len(got) == count, what="every value")
    finally:
        done.set()
        sampler.join()
    assert got == [seed % 251 for seed in range(count)]  # in order, each once
    assert most[0] > MAX_UNSENT  # the server had more than that waiting for it: the path this test is for
    assert not session.dead, session.dead
    assert watcher._transport._directory.shared.session() is session
    assert watcher._transport._directory.watch_stream.reconnects == 0
