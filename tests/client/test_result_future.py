"""An async write's one future: settled with its reply, it holds the result; what the write held goes once.

:class:`cast.client.write_replies.ResultFuture` is what ``add_async`` and the
other async writes return, and the future their reply's reader settles.
"""

from __future__ import annotations

import threading
from concurrent.futures import InvalidStateError
from typing import Any

import pytest
from cast_testing_pb2 import Pose

import cast
from cast.client.write_replies import ResultFuture, settle
from cast.core.records import WriteResult
from cast.errors import AlreadyExistsError, DeadlineExceededError
from cast.v1 import working_memory_pb2 as wm_pb2
from tests.client.shm_host import Host
from tests.client.shm_host import host as host  # the fixture, used by name


def _result(reply: wm_pb2.WriteReply) -> WriteResult:
    if reply.WhichOneof("result") == "error":
        raise AlreadyExistsError(reply.error.message)
    return WriteResult(reply.write.revision, reply.write.version)


def _reply(revision: int) -> wm_pb2.WriteReply:
    reply = wm_pb2.WriteReply(id=1)
    reply.write.revision, reply.write.version = revision, 1
    return reply


def _future(settled: list[Any]) -> ResultFuture[WriteResult]:
    return ResultFuture(_result, settled.append)


def test_a_reply_settles_it_with_the_converted_result_after_what_the_write_held_went() -> None:
    settled: list[Any] = []
    future = _future(settled)
    seen_in_callback: list[Any] = []
    future.add_done_callback(lambda f: seen_in_callback.append(list(settled)))
    settle(future, _reply(7), None)
    assert future.result(0) == WriteResult(7, 1)
    assert settled == [None] and seen_in_callback == [[None]]  # let go before the caller's callbacks ran


def test_a_reply_that_carries_an_error_fails_it_with_that_error() -> None:
    settled: list[Any] = []
    future = _future(settled)
    reply = wm_pb2.WriteReply(id=1)
    reply.error.message = "exists"
    settle(future, reply, None)
    with pytest.raises(AlreadyExistsError, match="exists"):
        future.result(0)
    assert len(settled) == 1 and isinstance(settled[0], AlreadyExistsError)


def test_a_reply_after_the_deadline_changes_nothing() -> None:
    settled: list[Any] = []
    future = _future(settled)
    settle(future, None, DeadlineExceededError("too late"))
    settle(future, _reply(3), None)  # the late reply: settle ignores it, as for any settled future
    with pytest.raises(InvalidStateError):
        future.set_result(_reply(3))
    with pytest.raises(DeadlineExceededError):
        future.result(0)
    assert len(settled) == 1 and isinstance(settled[0], DeadlineExceededError)


def test_a_reply_after_the_caller_cancelled_still_lets_the_write_go() -> None:
    settled: list[Any] = []
    future = _future(settled)
    assert future.cancel()
    settle(future, _reply(3), None)
    assert settled == [None] and future.cancelled()


def test_two_threads_settling_at_once_let_the_write_go_once() -> None:
    for _ in range(200):
        settled: list[Any] = []
        future = _future(settled)
        start = threading.Barrier(2)

        def reply(future: ResultFuture[WriteResult] = future, start: threading.Barrier = start) -> None:
            start.wait()
            settle(future, _reply(1), None)

        def expire(future: ResultFuture[WriteResult] = future, start: threading.Barrier = start) -> None:
            start.wait()
            settle(future, None, DeadlineExceededError("expired"))

        threads = [threading.Thread(target=reply), threading.Thread(target=expire)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(settled) == 1 and future.done()


def test_an_async_write_returns_the_future_its_reply_settles(host: Any) -> None:
    h: Host = host()
    c = h.component("writer")
    future = c.add_async("pose", Pose(x=1))
    assert type(future) is ResultFuture
    assert future.result(10).revision > 0
    again = c.add_async("pose", Pose(x=2))
    with pytest.raises(cast.AlreadyExistsError):
        again.result(10)
