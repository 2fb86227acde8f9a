"""Write requests in flight and their replies: the table of what is outstanding, settling, naming.

Shared by the two ways a component's Write-stream requests travel: the gRPC
``Write`` stream (:mod:`cast.client.write_stream`) and the shared-memory
session's socket (:mod:`cast.client.socket_writes`). Each keeps an
:class:`Outstanding` table under its own lock, since each wakes its own
threads as the table changes.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future, InvalidStateError
from typing import Any, Generic, TypeVar

from cast.errors import CastError, error_for_code
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = [
    "DRAIN_S", "Answered", "Expired", "Outstanding", "ResultFuture", "reply_result", "settle", "settle_replies", "what",
]

T = TypeVar("T")

DRAIN_S = 30.0
"""How long a new way for writes (a stream or session opened with a renewed token, the session's
socket after the gRPC stream) waits for what the old one has outstanding before taking over: no
write overtakes an earlier one."""

Answered = list[tuple[Future[wm_pb2.WriteReply], wm_pb2.WriteReply]]
"""Requests answered: each future with its reply."""

Expired = tuple[Future[wm_pb2.WriteReply], float, str]
"""A request past its deadline: its future, the timeout it had, and what it was (:func:`what`)."""


class Outstanding:
    """The requests sent and not answered yet: their futures, their deadlines, those nobody waits on.

    Ids are given here, in send order. Not locked: its owner calls it with
    its own lock held, and settles the futures it hands back after letting go.
    """

    def __init__(self) -> None:
        self.pending: dict[int, Future[wm_pb2.WriteReply]] = {}
        self.detached: set[int] = set()  # pending ids whose caller does not wait (async calls)
        self.deadlines: dict[int, tuple[float, float, str]] = {}  # pending id -> (deadline, its timeout, what)
        self._ids = itertools.count(1)

    def add(self, request: wm_pb2.WriteRequest, detached: bool, timeout: float | None,
            future: Future[Any] | None = None) -> Future[wm_pb2.WriteReply]:
        """Give ``request`` the next id and a future (``future``, or a new one); past ``timeout`` s it is expired.

        ``timeout`` None: never.
        """
        if future is None:
            future = Future()
        request.id = request_id = next(self._ids)
        self.pending[request_id] = future
        if timeout is not None:
            self.deadlines[request_id] = (time.monotonic() + timeout, timeout, what(request))
        if detached:
            self.detached.add(request_id)
        return future

    def answer(self, replies: Iterable[wm_pb2.WriteReply]) -> tuple[Answered, Answered]:
        """Take the requests ``replies`` answer, each with its reply (for :func:`settle_replies`).

        Two lists: those a caller waits for, and the detached ones, whose
        futures may have callbacks of the user's (an async write's). Those
        callbacks may write and wait in turn, so the reader settles them only
        once it has let go of what it reads, or their waits would wait for it.
        A reply to no outstanding request (its deadline passed, its caller has
        the error) is left out.
        """
        pop, detached, deadlines = self.pending.pop, self.detached, self.deadlines
        waited: Answered = []
        unwaited: Answered = []
        for reply in replies:
            future = pop(reply.id, None)
            if future is not None:
                deadlines.pop(reply.id, None)
                if reply.id in detached:
                    detached.discard(reply.id)
                    unwaited.append((future, reply))
                else:
                    waited.append((future, reply))
        return waited, unwaited

    def earliest(self) -> tuple[float, float, str] | None:
        """The earliest deadline, with its request's timeout and name; None when no request has one."""
        return min(self.deadlines.values()) if self.deadlines else None

    def take_expired(self, now: float) -> list[Expired]:
        """Take the requests whose deadline is ``now`` or earlier."""
        expired = []
        for request_id, (deadline, waited, name) in list(self.deadlines.items()):
            if deadline <= now:
                del self.deadlines[request_id]
                self.detached.discard(request_id)
                future = self.pending.pop(request_id, None)
                if future is not None:
                    expired.append((future, waited, name))
        return expired

    def take_all(self) -> list[Future[wm_pb2.WriteReply]]:
        """Take every outstanding request (the way they went ended)."""
        left = list(self.pending.values())
        self.pending.clear()
        self.detached.clear()
        self.deadlines.clear()
        return left


class ResultFuture(Future[T], Generic[T]):
    """An async write's future as its caller gets it: settled with the reply, it holds what ``convert`` makes of it.

    One future per async write where there were two (the reply's, and the
    caller's chained to it by a callback): each costs a condition variable
    and a lock, about a third of an async write's client CPU
    (docs/performance.md, "Pipelined writes with one future each").
    ``settled(error)`` runs once, when the future is settled, before its
    callbacks (``error`` None for a result): what the write held is let go.
    A reply that comes after its deadline settled the future changes
    nothing; one that comes after the caller cancelled it still lets go
    what the write held.
    """

    def __init__(self, convert: Callable[[wm_pb2.WriteReply], T],
                 settled: Callable[[BaseException | None], None]) -> None:
        super().__init__()
        self._convert = convert
        self._settled = [settled]  # popped once: list.pop is atomic, so two threads settling run it once

    def _settle(self, error: BaseException | None) -> None:
        try:
            settled = self._settled.pop()
        except IndexError:
            return
        settled(error)

    def set_result(self, result: Any) -> None:
        """Settle with ``result``, the write's reply: the converted value, or the error the reply carries."""
        try:
            value = self._convert(result)
        except BaseException as exc:  # noqa: BLE001 - every failure goes to the caller
            self.set_exception(exc)
            return
        self._settle(None)  # also when the caller cancelled it: the write is over all the same
        super().set_result(value)  # InvalidStateError when settled already (a reply after its deadline)

    def set_exception(self, exception: BaseException | None) -> None:
        """Fail it with ``exception``."""
        self._settle(exception)
        super().set_exception(exception)


def reply_result(reply: wm_pb2.WriteReply) -> wm_pb2.WriteReply:
    """The reply itself if it carries a result; the error the unary call would have raised otherwise."""
    if reply.WhichOneof("result") == "error":
        error = reply.error
        raise error_for_code(error.code, error.message or error.code, error.error_class)
    return reply


def settle(future: Future[wm_pb2.WriteReply], reply: wm_pb2.WriteReply | None, error: CastError | None) -> None:
    """Complete ``future`` with ``reply``, or fail it with ``error``; nothing if it is settled already."""
    try:
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(reply)  # type: ignore[arg-type]
    except InvalidStateError:
        pass  # settled already: its deadline passed


def settle_replies(answered: Answered) -> None:
    """Complete each future with its reply (:meth:`Outstanding.answer`'s list)."""
    for future, reply in answered:
        settle(future, reply, None)


def what(request: wm_pb2.WriteRequest) -> str:
    """How an error names the request: "add of 'x'", "lock of 'x'", "batch of 3 writes"."""
    kind = request.WhichOneof("operation") or "request"
    if kind == "batch":
        return f"batch of {len(request.batch.operations)} writes"
    body = getattr(request, kind)
    return f"{kind} of '{body.address.id}'"
