"""A component's writes and locks on one WorkingMemory.Write stream per server, each answered by id.

A unary call costs a whole gRPC call set-up and tear-down each way; on the
stream a write is one message each way, and many may be in flight
(:meth:`WriteStream.submit` returns a future). Writes are sent in call order
on one stream, which the server applies in arrival order, so a component's
writes keep their order.

The token is checked before each send (a ``stat`` of the token file at most
once a second, :class:`cast.client.credentials.TokenSource`); when the
orchestrator has renewed it, the stream is replaced by one opened with the
new token, after the old one's outstanding requests are answered (so no
write overtakes an earlier one). A stream that breaks fails its outstanding
requests with UnavailableError, as a broken unary call, and the next write
opens a new one.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
from collections.abc import Iterator
from concurrent.futures import Future, InvalidStateError

import grpc

from cast.client.channel import ServerLink, map_rpc_error
from cast.client.credentials import TokenSource
from cast.errors import CastError, DeadlineExceededError, UnavailableError, error_for_code
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["WriteStream", "reply_result"]

log = logging.getLogger("cast.client")

# How long a token change waits for the old stream's outstanding replies before opening the new one.
_DRAIN_S = 30.0


def reply_result(reply: wm_pb2.WriteReply) -> wm_pb2.WriteReply:
    """The reply itself if it carries a result; the error the unary call would have raised otherwise."""
    if reply.WhichOneof("result") == "error":
        error = reply.error
        raise error_for_code(error.code, error.message or error.code, error.error_class)
    return reply


def _settle(future: Future[wm_pb2.WriteReply], reply: wm_pb2.WriteReply | None, error: CastError | None) -> None:
    try:
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(reply)  # type: ignore[arg-type]
    except InvalidStateError:
        pass  # the caller gave up waiting (its deadline) and cancelled it


def _messages(requests: queue.SimpleQueue[wm_pb2.WriteRequest | None]) -> Iterator[wm_pb2.WriteRequests]:
    """The stream's messages: each request as soon as it is queued, with whatever queued up behind it.

    gRPC sends one message at a time; what is queued meanwhile goes in the
    next one, so many writes in flight share the per-message cost.
    """
    while True:
        first = requests.get()
        if first is None:
            return
        message = wm_pb2.WriteRequests()
        append = message.requests.append
        append(first)
        while True:
            try:
                more = requests.get_nowait()
            except queue.Empty:
                break
            if more is None:
                yield message
                return
            append(more)
        yield message


class _Call:
    """One open Write call: its request queue, outstanding futures and the thread reading replies."""

    def __init__(self, server: ServerLink, token: str) -> None:
        self.token = token
        self.endpoint = server.endpoint
        self.requests: queue.SimpleQueue[wm_pb2.WriteRequest | None] = queue.SimpleQueue()
        self.pending: dict[int, Future[wm_pb2.WriteReply]] = {}
        self.lock = threading.Lock()
        self.idle = threading.Condition(self.lock)  # notified when pending becomes empty
        self.broken = False
        self.ids = itertools.count(1)
        metadata = (("authorization", f"Bearer {token}"),)
        self.responses = server.wm.Write(_messages(self.requests), metadata=metadata)
        self.reader = threading.Thread(target=self._read, name="cast-write-replies", daemon=True)
        self.reader.start()

    def send(self, request: wm_pb2.WriteRequest) -> Future[wm_pb2.WriteReply]:
        """Queue ``request`` with the next id; the future of its reply. Call with :attr:`lock` held."""
        future: Future[wm_pb2.WriteReply] = Future()
        request.id = request_id = next(self.ids)
        self.pending[request_id] = future
        self.requests.put(request)
        return future

    def _read(self) -> None:
        status = "the server ended it"
        try:
            for message in self.responses:
                with self.lock:
                    pop = self.pending.pop
                    settled = [(pop(reply.id, None), reply) for reply in message.replies]
                    if not self.pending:
                        self.idle.notify_all()
                for future, reply in settled:
                    if future is not None:
                        _settle(future, reply, None)
        except grpc.RpcError as exc:
            status = str(map_rpc_error(exc))
        except Exception as exc:  # noqa: BLE001 - the thread must fail the outstanding calls whatever happened
            status = f"{type(exc).__name__}: {exc}"
        with self.lock:
            self.broken = True
            left = list(self.pending.values())
            self.pending.clear()
            self.idle.notify_all()
        for future in left:
            _settle(future, None, UnavailableError(
                f"the write stream to {self.endpoint} broke ({status}): this write may or may not have been "
                "applied; the client reconnects by itself, retry the call later"
            ))

    def drain(self, timeout: float) -> None:
        """Wait until every outstanding request is answered (or ``timeout``). Call with :attr:`lock` held."""
        self.idle.wait_for(lambda: not self.pending, timeout)

    def close(self) -> None:
        """Half-close: the server answers what it has and ends the call."""
        self.requests.put(None)

    def cancel(self) -> None:
        """End the call now; outstanding requests fail."""
        self.responses.cancel()  # type: ignore[no-untyped-call]


class WriteStream:
    """The Write stream of one component to one server, opened on the first write and after a break."""

    def __init__(self, server: ServerLink, tokens: TokenSource) -> None:
        self._server = server
        self._tokens = tokens
        self._lock = threading.Lock()  # one sender at a time: ids and queue order agree
        self._call: _Call | None = None
        self._closed = False

    def submit(self, request: wm_pb2.WriteRequest) -> Future[wm_pb2.WriteReply]:
        """Send ``request`` (its id is set here); the future of its reply (use :func:`reply_result`)."""
        token = self._tokens.token()
        with self._lock:
            if self._closed:
                raise UnavailableError("the component is closing: no more writes")
            call = self._call
            if call is None or call.broken or call.token != token:
                call = self._open(call, token)
            with call.lock:
                if not call.broken:
                    return call.send(request)
            call = self._open(call, token)  # it broke just now: one more try on a new call
            with call.lock:
                return call.send(request)

    def _open(self, old: _Call | None, token: str) -> _Call:
        if old is not None and not old.broken:
            with old.lock:
                old.drain(_DRAIN_S)  # the new token's stream must not overtake the old one's writes
            old.close()
        self._call = _Call(self._server, token)
        return self._call

    def call(self, request: wm_pb2.WriteRequest, timeout: float | None) -> wm_pb2.WriteReply:
        """Send ``request`` and wait for its result; its error raised as the unary call would.

        A refused token is re-read from its file once, and the request sent
        again if it changed (a refused request changed nothing).
        """
        reply = self._wait(self.submit(request), timeout)
        if reply.WhichOneof("result") == "error" and reply.error.code == "UNAUTHENTICATED" and self._tokens.refresh():
            reply = self._wait(self.submit(request), timeout)
        return reply_result(reply)

    @staticmethod
    def _wait(future: Future[wm_pb2.WriteReply], timeout: float | None) -> wm_pb2.WriteReply:
        try:
            return future.result(timeout)
        except TimeoutError:
            future.cancel()
            raise DeadlineExceededError(
                f"no reply to a write within {timeout} s: it may or may not have been applied"
            ) from None

    def close(self, timeout: float = 2.0) -> None:
        """Stop sending; wait up to ``timeout`` for outstanding replies, then end the stream."""
        with self._lock:
            self._closed = True
            call, self._call = self._call, None
        if call is None:
            return
        with call.lock:
            call.drain(timeout)
        call.close()
        call.reader.join(timeout)
        if call.reader.is_alive():
            call.cancel()
