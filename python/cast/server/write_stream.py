"""One WorkingMemory.Write call: a component's writes and locks on one stream, each answered by id.

Requests are applied in the order they arrive, each as the unary call of the
same name would (the same :class:`cast.core.access.Access` rules, so the same
permissions, versions and errors). A call that must wait - a lock held by
another component, or a journal that writers wait for - waits in a task of
its own, so the requests behind it are applied and answered meanwhile; its
reply then comes out of order, matched by id. The token is checked for every
request, so one that expires while the stream is open refuses the writes
after it, as the unary calls would. A stream's token cannot change (it is the
call's metadata) and its answer is the same until it expires, so the identity
is established at the first request and again only once the token's expiry
has come: for each request the answer verifying it would give, without the
cost (docs/decisions.md, "The Write stream verifies its token once until it
expires").
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

from cast.core.access import Access, Steps, resume_async, settle_at_once
from cast.core.records import Identity
from cast.core.system import System
from cast.errors import CastError, InvalidArgumentError
from cast.server.rpc import error_class
from cast.server.write_requests import batch_ops, lock_mode, write_op
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["WriteStream", "watch_woken"]

log = logging.getLogger("cast.server")

_Answer = Callable[[wm_pb2.WriteReply, Any], None]


class _Woken:
    """How many times a write woke a watch stream on the event loop so far (:func:`watch_woken` counts them)."""

    count = 0


def watch_woken() -> None:
    """A write woke a watch stream on the event loop: the replies of the write wait for its events to go first."""
    _Woken.count += 1


def _write_answer(reply: wm_pb2.WriteReply, result: Any) -> None:
    reply.write.revision = result.revision
    reply.write.version = result.version


def _batch_answer(reply: wm_pb2.WriteReply, results: Any) -> None:
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


class WriteStream:
    """One Write call of one component."""

    def __init__(self, system: System, caller: Callable[[], tuple[Identity, float]]) -> None:
        self._system = system
        self._caller = caller  # the caller's identity and its token's expiry (0: never), verified afresh
        self._who: Identity | None = None  # the caller, while its token has not expired
        self._until = 0.0
        self._ready: list[wm_pb2.WriteReply] = []  # replies not yet sent
        self._late = asyncio.Event()  # a waiting request was answered
        self._waiting: set[asyncio.Task[None]] = set()
        self.on_late: Callable[[], None] | None = None  # PROTOTYPE: the socket's transport sends late replies

    async def run(self, messages: AsyncIterator[wm_pb2.WriteRequests]) -> AsyncIterator[wm_pb2.WriteReplies]:
        """Yield the replies until the client has closed its side and every request is answered.

        While no request waits, this reads a message, applies it and sends
        its replies in one message, in one coroutine like a bare echo stream
        (each hand-off between tasks would cost an event-loop round per
        write). While some wait, it also watches for their late replies.
        Replies that are ready together go out in one message: with many
        requests in flight, the per-message cost of gRPC is shared by them.
        A message whose writes woke watch streams is answered after those
        streams had one turn of the loop: its events go out before its reply,
        so what watchers wait for does not queue behind the writer's
        acknowledgement (docs/performance.md, M8).
        """
        source = messages.__aiter__()
        reading: asyncio.Future[wm_pb2.WriteRequests] | None = None
        try:
            while True:
                woken = _Woken.count
                if reading is None and not self._waiting:
                    try:
                        message = await source.__anext__()
                    except StopAsyncIteration:
                        break
                    woken = _Woken.count
                    self._apply(message)
                else:
                    if reading is None:
                        reading = asyncio.ensure_future(source.__anext__())
                    late = asyncio.ensure_future(self._late.wait())
                    await asyncio.wait((reading, late), return_when=asyncio.FIRST_COMPLETED)
                    late.cancel()
                    self._late.clear()
                    if reading.done():
                        done, reading = reading, None
                        woken = _Woken.count
                        try:
                            self._apply(done.result())
                        except StopAsyncIteration:
                            break
                if self._ready:
                    if _Woken.count != woken:
                        # Events before acknowledgements: the watch streams these writes woke are ready to run;
                        # one turn of the loop lets them send their events before this reply costs its own send.
                        await asyncio.sleep(0)
                    yield self._take()
            while self._waiting:  # the client closed its side: answer what still waits, then end
                await asyncio.wait(set(self._waiting))
                if self._ready:
                    yield self._take()
            if self._ready:
                yield self._take()
        finally:
            if reading is not None:
                reading.cancel()
            for task in list(self._waiting):
                task.cancel()  # a lock still waiting for a client that left: give up the wait

    def _apply(self, message: wm_pb2.WriteRequests) -> None:
        for request in message.requests:
            self._handle(request)

    def _take(self) -> wm_pb2.WriteReplies:
        out = wm_pb2.WriteReplies()
        out.replies.extend(self._ready)
        self._ready.clear()
        return out

    def _handle(self, request: wm_pb2.WriteRequest) -> None:
        """Apply one request now; answer it now, or from a task if it must wait."""
        request_id = request.id
        reply = wm_pb2.WriteReply(id=request_id)
        try:
            kind = request.WhichOneof("operation")
            if kind is None:
                raise InvalidArgumentError(
                    f"write request {request_id} is empty: set add, overwrite, delete, batch, lock or unlock"
                )
            access = Access(self._system, self._identity())  # who, before what
            steps, answer = _call(access, kind, getattr(request, kind))
            try:
                step = next(steps)
            except StopIteration as done:
                answer(reply, done.value)
                self._put(reply)
                return
            pending, result = settle_at_once(self._system, steps, step)
            if pending is None:
                answer(reply, result)
                self._put(reply)
                return
        except CastError as exc:
            self._put(_error_reply(request_id, exc))
            return
        except Exception as exc:  # a bug answers this request, never ends the others
            log.exception("internal error in write request %d", request_id)
            self._put(_error_reply(request_id, _internal(exc)))
            return
        timeout = request.timeout_ms / 1000 if request.timeout_ms else None
        task = asyncio.ensure_future(self._finish(reply, steps, pending, answer, timeout))
        self._waiting.add(task)
        task.add_done_callback(self._waiting.discard)

    def _identity(self) -> Identity:
        """The caller now: verified at the first request and again each time its token's expiry has come."""
        who = self._who
        if who is None or (self._until and time.time() >= self._until):
            self._who = None  # an expired token is refused for every request after it too
            who, self._until = self._caller()
            self._who = who
        return who

    def _put(self, reply: wm_pb2.WriteReply) -> None:
        self._ready.append(reply)

    async def _finish(
        self,
        reply: wm_pb2.WriteReply,
        steps: Steps[Any],
        step: Any,
        answer: _Answer,
        timeout: float | None,
    ) -> None:
        try:
            result = await resume_async(self._system, steps, step, timeout)
        except CastError as exc:
            self._put(_error_reply(reply.id, exc))
        except Exception as exc:  # as in _handle: answer, never leave the request open
            log.exception("internal error in write request %d", reply.id)
            self._put(_error_reply(reply.id, _internal(exc)))
        else:
            answer(reply, result)
            self._put(reply)
        self._late.set()
        if self.on_late is not None:
            self.on_late()
