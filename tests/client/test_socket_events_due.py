"""The loop's list of socket watch streams due (cast.server.socket_events.Due): each served once, in the order woken.

A write path holds the list while it applies writes (``Due.hold``): the
socket streams they wake get no callback of their own, since the write path
serves them itself right after; a gRPC watch stream's task woken among them
keeps its place (``before_task_woken``). The unit tests drive a ``Due`` on a
real event loop with streams that record when they are served; the last test
runs the real server, two socket watchers and a writer on either write path
(a component's Write stream, a raw session's WRITES frames), and counts the
callbacks that found nothing to serve.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import cast
from cast.core.records import Identity
from cast.server import socket_events
from cast.server.socket_events import Due
from tests.client.shm_host import MIB, Host, image
from tests.client.shm_host import host as host  # the fixture, used by name
from tests.client.test_socket_writes import RawSession, add
from tests.conftest import wait_for


class _Stream:
    """A stream that records each time it is served; ``more`` batches pending after the first."""

    def __init__(self, name: str, served: list[str], more: int = 0) -> None:
        self.name = name
        self.served = served
        self.more = more

    def send_events(self) -> bool:
        self.served.append(self.name)
        if self.more:
            self.more -= 1
            return True
        return False


class _CountingLoop(asyncio.SelectorEventLoop):
    """An event loop that counts the callbacks scheduled on it."""

    scheduled = 0

    def call_soon(self, callback: Callable[..., object], *args: Any, context: Any = None) -> asyncio.Handle:
        self.scheduled += 1
        return super().call_soon(callback, *args, context=context)


@pytest.fixture
def loop() -> Iterator[_CountingLoop]:
    made = _CountingLoop()
    yield made
    made.close()


def _turns(loop: asyncio.AbstractEventLoop, count: int = 3) -> None:
    """Let the loop run what is scheduled, ``count`` turns."""
    for _ in range(count):
        loop.run_until_complete(asyncio.sleep(0))


def test_a_stream_woken_outside_a_write_path_is_served_by_a_callback_of_its_own(loop: _CountingLoop) -> None:
    served: list[str] = []
    due = Due(loop)
    due.add(_Stream("a", served))
    due.add(_Stream("b", served))
    assert served == []
    _turns(loop)
    assert served == ["a", "b"]


def test_streams_woken_while_held_and_served_by_the_write_path_get_no_callbacks(loop: _CountingLoop) -> None:
    served: list[str] = []
    due = Due(loop)
    a, b = _Stream("a", served), _Stream("b", served)
    before = loop.scheduled
    due.hold()
    due.add(a)
    due.add(b)
    due.add(a)  # woken twice: served once
    due.serve()
    due.release()
    assert served == ["a", "b"]
    assert loop.scheduled == before  # nothing left for the loop
    _turns(loop)
    assert served == ["a", "b"]


def test_streams_woken_while_held_and_not_served_are_served_in_order_once_released(loop: _CountingLoop) -> None:
    served: list[str] = []
    due = Due(loop)
    due.hold()
    due.add(_Stream("a", served))
    due.add(_Stream("b", served))
    due.release()
    assert served == []
    _turns(loop)
    assert served == ["a", "b"]


def test_a_task_woken_among_socket_streams_keeps_its_place(loop: _CountingLoop) -> None:
    served: list[str] = []
    due = Due(loop)
    due.hold()
    due.add(_Stream("a", served))
    socket_events.before_task_woken(due)
    loop.call_soon(served.append, "task")  # what waking a gRPC stream's task schedules
    due.add(_Stream("b", served))
    due.release()
    _turns(loop)
    assert served == ["a", "task", "b"]


def test_a_stream_with_more_pending_is_due_again_after_the_others(loop: _CountingLoop) -> None:
    served: list[str] = []
    due = Due(loop)
    due.hold()
    due.add(_Stream("a", served, more=1))
    due.add(_Stream("b", served))
    due.serve()
    due.release()
    assert served == ["a", "b"]
    _turns(loop)
    assert served == ["a", "b", "a"]


def test_nested_holds_leave_the_streams_to_the_outermost_release(loop: _CountingLoop) -> None:
    served: list[str] = []
    due = Due(loop)
    due.hold()
    due.hold()
    due.add(_Stream("a", served))
    due.release()
    _turns(loop)
    assert served == []  # still held
    due.release()
    _turns(loop)
    assert served == ["a"]


@pytest.mark.parametrize("path", ["write stream", "writes frames"])
def test_a_write_path_leaves_no_callback_that_finds_its_stream_served(
    host: Callable[..., Host], monkeypatch: pytest.MonkeyPatch, path: str
) -> None:
    """The Write stream and the session's WRITES serve their socket watchers themselves: no callback for nothing."""
    idle = {"count": 0}
    serve_one = Due._serve_one

    def counting(self: Due, stream: Any) -> None:
        if stream not in self._streams:
            idle["count"] += 1
        serve_one(self, stream)

    monkeypatch.setattr(Due, "_serve_one", counting)
    h = host()
    watchers = [h.component(f"watcher{i}") for i in range(2)]
    got: list[list[int]] = [[], []]
    for watcher, seen in zip(watchers, got, strict=True):
        watcher.on_change(
            cast.address_filter("img", include_entry=True),
            lambda change, seen=seen: seen.append(change.revision),
        )
    if path == "write stream":
        writer = h.component("writer")
        writer.add("img", image(MIB, 0))
        for seed in range(1, 21):
            writer.overwrite("img", image(MIB, seed))
    else:
        raw = RawSession(h, h.signer.issue(Identity("writer", "vision")))
        try:
            raw.write(add(1, "img", b"0"))
            for request_id in range(2, 22):
                raw.write(add(request_id, "img", bytes([request_id]), overwrite=True))
            replies = raw.replies(21)
        finally:
            raw.close()
        assert all(not reply.HasField("error") for reply in replies)
    wait_for(lambda: all(len(seen) == 21 for seen in got), what="every write")
    assert got[0] == got[1] == sorted(got[0])
    # A callback per watcher and write (about 40) before the write paths held the list; now none, or
    # one at most when a connection that had drained was due at the same moment.
    assert idle["count"] <= 2
