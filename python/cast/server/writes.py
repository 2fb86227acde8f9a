"""A component's write requests, applied in arrival order and answered by id: what both write transports share.

The Write stream (:mod:`cast.server.write_stream`, a gRPC call) and the
shared-memory session's WRITES frames (:mod:`cast.server.socket_writes`, the
session's Unix socket) carry the same ``cast.v1.WriteRequests`` and answer
with the same ``cast.v1.WriteReplies``; this module is what they share.
Requests are applied as the unary call of the same name would (the same
:class:`cast.core.access.Access` rules, so the same permissions, versions
and errors). A call that must wait - a lock held by another component, or a
journal that writers wait for - waits in a task of its own, so the requests
behind it are applied and answered meanwhile; its reply then comes out of
order, matched by id, and the transport is told (``on_late``).

The caller's identity is checked for every request: a token that expires
while the transport is open refuses the requests after it, as the unary
calls would. A transport's token cannot change (the stream's metadata, the
session's HELLO) and its answer is the same until it expires, so the
identity is established at the first request and again only once the
token's expiry has come: for each request the answer verifying it would
give, without the cost (docs/decisions.md, "The Write stream verifies its
token once until it expires").
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Iterable
from typing import Any, ClassVar

from cast.core.access import Access, Steps, resume_async, settle_at_once
from cast.core.records import Identity
from cast.core.shared import SharedSession
from cast.core.system import System
from cast.errors import CastError, InvalidArgumentError
from cast.server import socket_events
from cast.server.conversions import fill_entry
from cast.server.rpc import error_class
from cast.server.write_requests import batch_ops, lock_mode, write_op
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["Writes", "watch_woken", "woken"]

log = logging.getLogger("cast.server")

_Answer = Callable[[wm_pb2.WriteReply, Any], None]


class _Woken:
    """How many times a write woke a gRPC watch stream's task on the event loop so far (:func:`watch_woken`)."""

    count: ClassVar[int] = 0


def watch_woken() -> None:
    """A write woke a gRPC watch stream's task on the event loop: the write's replies wait for its events to go first.

    Watch streams whose events go on the session's socket are not counted:
    the write path sends their events itself before the replies
    (:func:`cast.server.socket_events.serve`).
    """
    _Woken.count += 1


def woken() -> int:
    """How many times writes woke gRPC watch streams so far: a transport compares it before and after applying.

    When it moved, the Write stream and the session's WRITES let the loop turn
    once before they send the replies, so that the events those streams send
    go out before the writer's acknowledgement (docs/performance-m8.md, "Where
    the time of one frame goes"). A
    unary write or Batch does not wait for them (docs/client-protocol.md).
    """
    return _Woken.count


def _write_answer(reply: wm_pb2.WriteReply, result: Any) -> None:
    reply.write.revision = result.revision
    reply.write.version = result.version


def _batch_answer(reply: wm_pb2.WriteReply, results: Any) -> None:
    reply.batch.SetInParent()  # a batch of no operations is answered too, with no results
    add = reply.batch.results.add
    for r in results:
        add(revision=r.revision, version=r.version)


def _lock_answer(reply: wm_pb2.WriteReply, depth: Any) -> None:
    reply.lock.depth = depth


def _unlock_answer(reply: wm_pb2.WriteReply, depth: Any) -> None:
    reply.unlock.depth = depth


def _call(access: Access, kind: str, body: Any) -> tuple[Steps[Any], _Answer]:
    """The steps of one request and how its result goes into the reply."""
    if kind == "add" or kind == "overwrite" or kind == "delete":
        return access.write(write_op(body, access)), _write_answer
    if kind == "batch":
        return access.batch(batch_ops(body, access)), _batch_answer
    address = body.address
    if kind == "lock":
        mode = lock_mode(body.mode)
        return access.lock(address.subarchitecture, address.id, mode, body.no_wait), _lock_answer
    return access.unlock(address.subarchitecture, address.id), _unlock_answer


class _Answered:
    """A request's answer, its reply not yet made: made when the transport takes the replies, after the events.

    Protobuf's reply objects cost tens of microseconds on a 30 Hz write's cold
    caches; made here, that cost would come before the write's events reach
    its watchers (docs/performance-m8.md, "The write hop without protobuf's
    objects").
    """

    __slots__ = ("answer", "request_id", "result")

    def __init__(self, request_id: int, answer: _Answer, result: Any) -> None:
        self.request_id = request_id
        self.answer = answer
        self.result = result

    def reply(self) -> wm_pb2.WriteReply:
        """The reply message (an internal error's, should the answer not fit it: as when it was made at once)."""
        reply = wm_pb2.WriteReply(id=self.request_id)
        try:
            self.answer(reply, self.result)
        except Exception as exc:  # a bug answers this request, never ends the others
            log.exception("internal error in write request %d", self.request_id)
            return _error_reply(self.request_id, _internal(exc))
        return reply


def _error_reply(request_id: int, exc: CastError) -> wm_pb2.WriteReply:
    reply = wm_pb2.WriteReply(id=request_id)
    reply.error.code = exc.code
    reply.error.message = exc.message
    reply.error.error_class = error_class(exc)
    return reply


def _internal(exc: Exception) -> CastError:
    error = CastError(f"internal server error: {type(exc).__name__}: {exc}")
    error.code = "INTERNAL"
    return error


class Writes:
    """One component's requests on one transport: applied in order, replies collected until the transport takes them.

    ``caller`` gives the caller's identity and its token's expiry (0: never),
    verified afresh; ``on_late`` is called on the loop when a request that
    waited has been answered (its reply is ready); ``session``: the
    shared-memory session whose socket carries the requests, on which a
    get's large value is lent (None, the gRPC stream: values as bytes).
    """

    def __init__(self, system: System, caller: Callable[[], tuple[Identity, float]],
                 on_late: Callable[[], None], session: SharedSession | None = None) -> None:
        self._system = system
        self._session = session
        self._caller = caller
        self._on_late = on_late
        self._who: Identity | None = None  # the caller, while its token has not expired
        self._until = 0.0
        self._ready: list[wm_pb2.WriteReply | _Answered] = []  # replies not yet sent, in order
        self.waiting: set[asyncio.Task[None]] = set()  # requests that wait (locks, a journal)
        self._due = socket_events.due_on(asyncio.get_running_loop())  # the loop's socket watch streams due

    @property
    def ready(self) -> bool:
        """Whether replies wait to be sent."""
        return bool(self._ready)

    def apply(self, requests: Iterable[wm_pb2.WriteRequest]) -> None:
        """Apply requests in order: each is answered now or, if it must wait, later.

        The socket watchers' events of these requests are sent before this
        returns, unless the requests also woke gRPC watch streams' tasks
        (:func:`woken` moved): the transport then lets the loop turn before
        its replies, and the socket streams are served by their callbacks in
        the order woken. Meanwhile the loop's list of socket streams is held
        (:meth:`cast.server.socket_events.Due.hold`), so that the streams
        these requests wake get no callback only to find themselves served.
        """
        before = _Woken.count
        due = self._due
        due.hold()
        try:
            for request in requests:
                self._handle(request)
            if _Woken.count == before:
                due.serve()
        finally:
            due.release()

    def take(self) -> wm_pb2.WriteReplies:
        """The replies ready now, in one message (several replies share the cost of a message)."""
        out = wm_pb2.WriteReplies()
        out.replies.extend([r if isinstance(r, wm_pb2.WriteReply) else r.reply() for r in self._ready])
        self._ready.clear()
        return out

    def cancel(self) -> None:
        """The transport ended: requests still waiting give up (a lock nobody will be told of)."""
        for task in list(self.waiting):
            task.cancel()

    def _handle(self, request: wm_pb2.WriteRequest) -> None:
        """Apply one request now; answer it now, or from a task if it must wait."""
        request_id = request.id
        try:
            kind = request.WhichOneof("operation")
            if kind is None:
                raise InvalidArgumentError(
                    f"write request {request_id} is empty: set add, overwrite, delete, batch, lock, unlock or get"
                )
            access = Access(self._system, self._identity())  # who, before what
            if kind == "get":  # a read never waits: answered here, in order with the writes around it
                self._ready.append(self._get(access, request_id, request.get, request.read_call))
                return
            steps, answer = _call(access, kind, getattr(request, kind))
            try:
                step = next(steps)
            except StopIteration as done:
                self._ready.append(_Answered(request_id, answer, done.value))
                return
            pending, result = settle_at_once(self._system, steps, step)
            if pending is None:
                self._ready.append(_Answered(request_id, answer, result))
                return
        except CastError as exc:
            self._ready.append(_error_reply(request_id, exc))
            return
        except Exception as exc:  # a bug answers this request, never ends the others
            log.exception("internal error in write request %d", request_id)
            self._ready.append(_error_reply(request_id, _internal(exc)))
            return
        timeout = request.timeout_ms / 1000 if request.timeout_ms else None
        task = asyncio.ensure_future(self._finish(request_id, steps, pending, answer, timeout))
        self.waiting.add(task)
        task.add_done_callback(self.waiting.discard)

    def _get(self, access: Access, request_id: int, body: wm_pb2.GetRequest,
             read_call: int) -> wm_pb2.WriteReply:
        """A get's reply: the entry, its large value lent on the session's ``read_call`` when there is one."""
        reply = wm_pb2.WriteReply(id=request_id)
        address = body.address
        record = access.get(address.subarchitecture, address.id)
        session = self._session
        lent = access.lend(session, read_call, record.shared) if session is not None and read_call else None
        fill_entry(reply.get.entry, record, lent)
        return reply

    def _identity(self) -> Identity:
        """The caller now: verified at the first request and again each time its token's expiry has come."""
        who = self._who
        if who is None or (self._until and time.time() >= self._until):
            self._who = None  # an expired token is refused for every request after it too
            who, self._until = self._caller()
            self._who = who
        return who

    async def _finish(
        self,
        request_id: int,
        steps: Steps[Any],
        step: Any,
        answer: _Answer,
        timeout: float | None,
    ) -> None:
        try:
            result = await resume_async(self._system, steps, step, timeout)
        except CastError as exc:
            self._ready.append(_error_reply(request_id, exc))
        except Exception as exc:  # as in _handle: answer, never leave the request open
            log.exception("internal error in write request %d", request_id)
            self._ready.append(_error_reply(request_id, _internal(exc)))
        else:
            self._ready.append(_Answered(request_id, answer, result))
        self._on_late()
