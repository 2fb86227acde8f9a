"""One WorkingMemory.Write call: a component's writes and locks on one stream, each answered by id.

Requests are applied in the order they arrive, each as the unary call of the
same name would (the same :class:`cast.core.access.Access` rules, so the same
permissions, versions and errors). A call that must wait - a lock held by
another component, or a journal that writers wait for - waits in a task of
its own, so the requests behind it are applied and answered meanwhile; its
reply then comes out of order, matched by id. The token is checked on every
request, so one that expires while the stream is open refuses the writes
after it, as the unary calls would.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Callable
from typing import Any

from cast.core.access import Access, Steps, resume_async, settle_at_once
from cast.core.system import System
from cast.errors import CastError, InvalidArgumentError
from cast.server.rpc import Authenticator, Context, error_class
from cast.server.write_requests import batch_ops, lock_mode, write_op
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["WriteStream"]

log = logging.getLogger("cast.server")

_Answer = Callable[[wm_pb2.WriteReply, Any], None]


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
        return access.write(write_op(body)), _write_answer
    if kind == "batch":
        return access.batch(batch_ops(body)), _batch_answer
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

    def __init__(self, system: System, auth: Authenticator, context: Context) -> None:
        self._system = system
        self._auth = auth
        self._context = context
        self._replies: asyncio.Queue[wm_pb2.WriteReply | None] = asyncio.Queue()
        self._waiting: set[asyncio.Task[None]] = set()

    async def run(self, messages: AsyncIterator[wm_pb2.WriteRequests]) -> AsyncIterator[wm_pb2.WriteReplies]:
        """Yield the replies until the client has closed its side and every request is answered.

        Replies that are ready together go out in one message: with many
        requests in flight, the per-message cost of gRPC is shared by them.
        """
        reader = asyncio.ensure_future(self._read(messages))
        replies = self._replies
        try:
            while True:
                reply = await replies.get()
                if reply is None:
                    return
                out = wm_pb2.WriteReplies()
                out.replies.append(reply)
                ended = False
                while not replies.empty():
                    more = replies.get_nowait()
                    if more is None:
                        ended = True
                        break
                    out.replies.append(more)
                yield out
                if ended:
                    return
        finally:
            reader.cancel()
            for task in list(self._waiting):
                task.cancel()  # a lock still waiting for a client that left: give up the wait

    async def _read(self, messages: AsyncIterator[wm_pb2.WriteRequests]) -> None:
        try:
            async for message in messages:
                for request in message.requests:
                    self._handle(request)
            while self._waiting:
                await asyncio.wait(set(self._waiting))
        finally:
            self._replies.put_nowait(None)

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
            access = Access(self._system, self._auth.identify(self._context))  # who, before what
            steps, answer = _call(access, kind, getattr(request, kind))
            try:
                step = next(steps)
            except StopIteration as done:
                answer(reply, done.value)
                self._replies.put_nowait(reply)
                return
            pending, result = settle_at_once(self._system, steps, step)
            if pending is None:
                answer(reply, result)
                self._replies.put_nowait(reply)
                return
        except CastError as exc:
            self._replies.put_nowait(_error_reply(request_id, exc))
            return
        except Exception as exc:  # a bug answers this request, never ends the others
            log.exception("internal error in write request %d", request_id)
            self._replies.put_nowait(_error_reply(request_id, _internal(exc)))
            return
        timeout = request.timeout_ms / 1000 if request.timeout_ms else None
        task = asyncio.ensure_future(self._finish(reply, steps, pending, answer, timeout))
        self._waiting.add(task)
        task.add_done_callback(self._waiting.discard)

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
            self._replies.put_nowait(_error_reply(reply.id, exc))
            return
        except Exception as exc:  # as in _handle: answer, never leave the request open
            log.exception("internal error in write request %d", reply.id)
            self._replies.put_nowait(_error_reply(reply.id, _internal(exc)))
            return
        answer(reply, result)
        self._replies.put_nowait(reply)
