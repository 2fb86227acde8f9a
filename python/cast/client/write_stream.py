"""A component's writes and locks on one WorkingMemory.Write stream per server, each answered by id.

A unary call costs a whole gRPC call set-up and tear-down each way; on the
stream a write is one message each way, and many may be in flight
(:meth:`WriteStream.submit` returns a future). Writes are sent in call order
on one stream, which the server applies in arrival order, so a component's
writes keep their order.

While the component has a shared-memory session with the server (on its
host), every request goes on the session's socket instead, with the same
rules (:mod:`cast.client.socket_writes`); switching waits until what the gRPC
call has outstanding was answered, so that no request overtakes an earlier
one. Its single-entry reads go there too (:meth:`WriteStream.read`): a frame
each way costs a fraction of a unary call.

The token is checked before each send (a ``stat`` of the token file at most
once a second, :class:`cast.client.credentials.TokenSource`); when the
orchestrator has renewed it, the stream is replaced by one opened with the
new token, after the old one's outstanding requests are answered (so no
write overtakes an earlier one). A stream that breaks fails its outstanding
requests with UnavailableError, as a broken unary call, and the next write
opens a new one.

Every request has a deadline (the call timeout; a blocking lock's own timeout
plus :data:`LOCK_REPLY_MARGIN_S`). A thread per stream watches them: when the
oldest outstanding request passes its deadline, its caller gets
DeadlineExceededError and the stream is ended, since a server that answers
nothing in that time is hung (or the path to it is); the others fail with
UnavailableError, and the next write opens a new stream. Keepalive alone would
notice a hung server only when the connection's ping goes unanswered.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from typing import Any, cast

import grpc

from cast.client.channel import MAX_MESSAGE_BYTES, ServerLink, map_rpc_error
from cast.client.credentials import TokenSource
from cast.client.socket_writes import SessionWrites
from cast.client.write_replies import DRAIN_S, Answered, Outstanding, reply_result, settle, settle_replies
from cast.errors import (
    CastError,
    DeadlineExceededError,
    InvalidArgumentError,
    UnauthenticatedError,
    UnavailableError,
)
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["LOCK_REPLY_MARGIN_S", "WriteStream"]

log = logging.getLogger("cast.client")

# What one message gathers of queued requests: large values in flight (64 images of 1 MiB) must not
# make a message over gRPC's limit, which would break the stream for every write on it.
_MESSAGE_BYTES = 4 * 1024 * 1024
# The largest request sent: gRPC's message limit, less room for the message's own framing.
_MAX_REQUEST_BYTES = MAX_MESSAGE_BYTES - 1024

LOCK_REPLY_MARGIN_S = 1.0
"""How much longer than a blocking lock's own timeout the client waits for the server's answer.

The server ends the wait itself at the timeout (DEADLINE_EXCEEDED); the margin is the answer's way
back. Past it the server is taken for hung, as for any other request past its deadline.
"""


def _messages(requests: queue.SimpleQueue[tuple[wm_pb2.WriteRequest, int] | None]) -> Iterator[wm_pb2.WriteRequests]:
    """The stream's messages: each request as soon as it is queued, with whatever queued up behind it.

    gRPC sends one message at a time; what is queued meanwhile goes in the
    next one (up to about :data:`_MESSAGE_BYTES`), so many writes in flight
    share the per-message cost. Queue items are (request, its size).
    """
    carried: tuple[wm_pb2.WriteRequest, int] | None = None
    while True:
        item = carried if carried is not None else requests.get()
        carried = None
        if item is None:
            return
        message = wm_pb2.WriteRequests()
        append = message.requests.append
        append(item[0])
        total = item[1]
        while total < _MESSAGE_BYTES:
            try:
                more = requests.get_nowait()
            except queue.Empty:
                break
            if more is None:
                yield message
                return
            if total + more[1] > _MESSAGE_BYTES:
                carried = more  # it starts the next message
                break
            append(more[0])
            total += more[1]
        yield message


class _Call:
    """One open Write call: its request queue, outstanding futures, and who reads the replies.

    Replies are read by a thread that waits for one (leader/follower): a
    caller waiting for its own reply reads the stream itself while nobody
    else does, settling every reply it finds, so a sequential write costs no
    hand-off to a reader thread and back. The pump thread reads only for
    futures nobody waits on (the async calls) and to see the end of a call
    that broke while idle. The watch thread ends the call when a request
    passes its deadline (the module's docstring).
    """

    def __init__(self, server: ServerLink, token: str, look_every: float) -> None:
        self.token = token
        self.endpoint = server.endpoint
        self.requests: queue.SimpleQueue[tuple[wm_pb2.WriteRequest, int] | None] = queue.SimpleQueue()
        self.outstanding = Outstanding()
        self.lock = threading.Lock()
        # Followers (and drain) wait on `changed`, the pump on `pump_wake`, the watch thread on
        # `watch_wake`: notifying a condition nobody waits on is cheap, waking a thread that only goes
        # back to sleep is not (on every write).
        self.changed = threading.Condition(self.lock)  # replies settled, reader left, or the call ended
        self.pump_wake = threading.Condition(self.lock)  # a detached request, the reader left, or the end
        self.watch_wake = threading.Condition(self.lock)  # a deadline earlier than the watch thread's, or the end
        self.followers = 0  # threads waiting on `changed`
        self.reading = False  # a thread is reading the stream (at most one)
        self.ended = False  # gRPC reported the call over: read what is left, then it is broken
        self.broken = False  # over: nothing more will be read; the next write opens a new call
        self.stalled = ""  # why the watch thread ended the call (a request past its deadline)
        # The watch thread looks again at the latest by `watch_until` (None: when told). While requests
        # are sent it keeps looking every `look_every` s, so that a sender need not wake it each time.
        self.watch_until: float | None = None
        self.sent = False  # a request was sent since the watch thread last looked
        self.look_every = look_every
        metadata = (("authorization", f"Bearer {token}"),)
        # The stubs' type (an iterator) hides what the call object also is: a grpc.Future with a next().
        self.responses: Any = cast(Any, server.open_stream(server.wm.Write, _messages(self.requests),
                                                           metadata=metadata))
        self.responses.add_done_callback(self._on_done)
        self.pump = threading.Thread(target=self._pump, name="cast-write-replies", daemon=True)
        self.pump.start()
        server.track(self.pump)
        self.watch = threading.Thread(target=self._watch, name="cast-write-deadlines", daemon=True)
        self.watch.start()
        server.track(self.watch)

    def send(self, request: wm_pb2.WriteRequest, size: int, detached: bool,
             timeout: float | None, future: Future[Any] | None = None) -> Future[wm_pb2.WriteReply]:
        """Queue ``request`` (``size`` bytes) with the next id; the future of its reply. Call with :attr:`lock` held.

        ``timeout``: seconds until its deadline (None: none, a lock that waits as long as it takes).
        ``future``: the one to settle with the reply (a :class:`ResultFuture`), else a new one.
        """
        future = self.outstanding.add(request, detached, timeout, future)
        if timeout is not None:
            self.sent = True
            deadline = self.outstanding.deadlines[request.id][0]
            if self.watch_until is None or deadline < self.watch_until:
                self.watch_wake.notify()
        if detached:
            self.pump_wake.notify()  # the pump reads for it
        self.requests.put((request, size))
        return future

    def _on_done(self, _: object) -> None:
        with self.lock:
            self.ended = True
            self._wake_all()

    def _lead(self) -> Answered | None:
        """Read one message and settle the replies callers wait for (the caller is the reader).

        The async writes it answered, for the reader to settle once it let go of the stream (their
        futures' callbacks may write and wait, :meth:`Outstanding.answer`); None once the call is over.
        """
        try:
            message = next(self.responses)
        except StopIteration:
            self._fail(None, "the server ended it")
            return None
        except grpc.RpcError as exc:
            error = map_rpc_error(exc)
            self._fail(error, self.stalled or str(error))
            return None
        except Exception as exc:  # noqa: BLE001 - whatever happened, the outstanding calls must fail
            self._fail(None, f"{type(exc).__name__}: {exc}")
            return None
        with self.lock:
            waited, unwaited = self.outstanding.answer(message.replies)
        settle_replies(waited)
        if self.followers:  # read without the lock: a follower counts itself before it checks its future
            with self.lock:
                self.changed.notify_all()  # followers whose reply this was, and drain()
        return unwaited

    def _fail(self, error: CastError | None, status: str) -> None:
        self.requests.put(None)  # ends the request iterator, and with it gRPC's thread that reads it
        with self.lock:
            self.broken = True
            left = self.outstanding.take_all()
        for future in left:
            if error is not None and error.code == "UNAUTHENTICATED" and not self.stalled:
                # Refused when it opened, before any request was read: nothing was applied.
                settle(future, None, error)
                continue
            settle(future, None, UnavailableError(
                f"the write stream to {self.endpoint} broke ({status}): this write may or may not have been "
                "applied; the client reconnects by itself, retry the call later"
            ))
        with self.lock:
            self._wake_all()  # the waiters of what just failed, the pump and the watch thread (to end)

    def _release(self) -> None:
        with self.lock:
            self.reading = False
            if self.followers:
                self.changed.notify_all()  # one of them reads next
            if self.outstanding.detached or self.ended:
                self.pump_wake.notify()

    def _wake_all(self) -> None:
        """Wake followers, the pump and the watch thread. Call with :attr:`lock` held."""
        self.changed.notify_all()
        self.pump_wake.notify()
        self.watch_wake.notify()

    def wait(self, future: Future[wm_pb2.WriteReply]) -> wm_pb2.WriteReply:
        """The reply of ``future``: read the stream while nobody else does, else wait for who does.

        The reader returns when the reply arrives or the call ends; the watch
        thread settles a request past its deadline and ends the call, so no
        wait outlasts the request's deadline.
        """
        while True:
            with self.lock:
                # Counted before the future is checked: the reader settles, then looks at the count.
                self.followers += 1
                try:
                    while not future.done() and (self.reading or self.broken):
                        self.changed.wait()
                finally:
                    self.followers -= 1
                if future.done():
                    break
                self.reading = True
            unwaited: Answered | None = []
            try:
                while not future.done() and unwaited == []:
                    unwaited = self._lead()
            finally:
                self._release()
            settle_replies(unwaited or [])
        return future.result()

    def _pump(self) -> None:
        while True:
            with self.lock:
                while not self.broken and (self.reading or not (self.outstanding.detached or self.ended)):
                    self.pump_wake.wait()
                if self.broken:
                    return
                self.reading = True
            try:
                unwaited = self._lead()
            finally:
                self._release()
            if unwaited is None:
                return
            settle_replies(unwaited)

    def _watch(self) -> None:
        """End the call when an outstanding request passes its deadline (the module's docstring)."""
        with self.lock:
            while True:
                if self.broken:
                    return
                now = time.monotonic()
                earliest = self.outstanding.earliest()
                if earliest is not None:
                    deadline, timeout, what = earliest
                    if deadline <= now:
                        break
                    self.watch_until = deadline
                elif self.sent:
                    self.watch_until = now + self.look_every
                else:
                    self.watch_until = None
                self.sent = False
                self.watch_wake.wait(None if self.watch_until is None else self.watch_until - now)
            self.stalled = (f"{self.endpoint} answered no request within its deadline ({what} waited {timeout:g} s): "
                            "the server looks hung, so the stream was ended")
            expired = self.outstanding.take_expired(now)
            self.changed.notify_all()  # followers whose request expired
        for future, waited, what in expired:
            settle(future, None, DeadlineExceededError(
                f"no reply from {self.endpoint} to the {what} within {waited:g} s: it may or may not have been "
                "applied; the write stream was ended and the next write opens a new one"
            ))
        self.responses.cancel()  # the reader sees the end and fails the others

    def drain(self, timeout: float) -> None:
        """Wait until every outstanding request is answered (or ``timeout``). Call with :attr:`lock` held."""
        self.followers += 1
        try:
            pending = self.outstanding.pending
            self.changed.wait_for(lambda: not pending, timeout)
        finally:
            self.followers -= 1

    def close(self) -> None:
        """Half-close: the server answers what it has and ends the call."""
        self.requests.put(None)

    def cancel(self) -> None:
        """End the call now; outstanding requests fail."""
        self.responses.cancel()


class WriteStream:
    """The Write stream of one component to one server, opened on the first write and after a break."""

    def __init__(self, server: ServerLink, tokens: TokenSource, call_timeout: float) -> None:
        self._server = server
        self._tokens = tokens
        self._timeout = call_timeout
        self._lock = threading.Lock()  # one sender at a time: ids and queue order agree
        self._call: _Call | None = None
        self._closed = False

    def submit(self, request: wm_pb2.WriteRequest, timeout: float | None = -1.0,
               future: Future[Any] | None = None) -> Future[wm_pb2.WriteReply]:
        """Send ``request`` (its id is set here) without waiting; the future of its reply (use :func:`reply_result`).

        The pump thread reads its reply; past ``timeout`` (-1: the call timeout) the future fails with
        DeadlineExceededError. ``future``: the one settled with the reply (a :class:`ResultFuture`), else a new one.
        """
        return self._submit(request, True, self._timeout if timeout == -1.0 else timeout, future)[1]

    def _submit(self, request: wm_pb2.WriteRequest, detached: bool, timeout: float | None,
                future: Future[Any] | None = None) -> tuple[_Call | SessionWrites, Future[wm_pb2.WriteReply]]:
        size = request.ByteSize()
        if size > _MAX_REQUEST_BYTES:
            # Sent, it would end the stream (and every write in flight on it) with RESOURCE_EXHAUSTED.
            raise InvalidArgumentError(
                f"write request of {size} bytes is over gRPC's message limit of {MAX_MESSAGE_BYTES} bytes: "
                "write smaller values, or split the batch"
            )
        token = self._tokens.token()
        with self._lock:
            if self._closed:
                raise UnavailableError("the component is closing: no more writes")
            writes = self._session_writes(token, timeout)
            if writes is not None:
                self._drain_call()
                sent = writes.send(request, size, detached, timeout, future)
                if sent is not None:
                    return writes, sent
                # The session ended just now: the gRPC stream takes it.
            call = self._call
            if call is None or call.broken or call.token != token:
                call = self._open(call, token)
            with call.lock:
                if not call.broken:
                    return call, call.send(request, size, detached, timeout, future)
            call = self._open(call, token)  # it broke just now: one more try on a new call
            with call.lock:
                if not call.broken:
                    return call, call.send(request, size, detached, timeout, future)
        raise UnavailableError(
            f"server {self._server.endpoint} unavailable: the write stream could not be opened, so this write "
            "was not sent; the client reconnects by itself, retry the call later"
        )

    def _drain_call(self) -> None:
        """Wait until the gRPC call has nothing outstanding: no request on the socket overtakes one still there.

        Called with :attr:`_lock` held; at once when the call has nothing outstanding.
        """
        call = self._call
        if call is not None and not call.broken:
            with call.lock:
                call.drain(DRAIN_S)

    def _session_writes(self, token: str, timeout: float | None) -> SessionWrites | None:
        """The session's socket while there is a session with the server (opened on the way if need be)."""
        link = self._server.shared
        if link is None:
            return None
        session = link.session(self._timeout if timeout is None else timeout, token)
        return session.writes if session is not None else None

    def _open(self, old: _Call | None, token: str) -> _Call:
        if old is not None and not old.broken:
            with old.lock:
                old.drain(DRAIN_S)  # the new token's stream must not overtake the old one's writes
            old.close()
        self._call = _Call(self._server, token, self._timeout)
        return self._call

    def call(self, request: wm_pb2.WriteRequest, timeout: float | None) -> wm_pb2.WriteReply:
        """Send ``request`` and wait for its result, at most ``timeout`` s (None: as long as it takes).

        Its error is raised as the unary call would; DeadlineExceededError past
        ``timeout``. A refused token is re-read from its file once, and the
        request sent again if it changed (a refused request changed nothing).
        """
        call, future = self._submit(request, False, timeout)
        try:
            reply = call.wait(future)
        except UnauthenticatedError:
            if not self._tokens.refresh():
                raise
            reply = self._retry(request, timeout)
        else:
            refused = reply.WhichOneof("result") == "error" and reply.error.code == "UNAUTHENTICATED"
            if refused and self._tokens.refresh():
                reply = self._retry(request, timeout)
        return reply_result(reply)

    def read(self, writes: SessionWrites, request: wm_pb2.WriteRequest,
             timeout: float | None) -> wm_pb2.WriteReply | None:
        """Send a read (a get) on a session's socket, after this stream's writes; its reply, None if the session ended.

        The read's lent value, if any, belongs to the session whose socket
        carries it, so it goes on ``writes`` (that session's) or not at all;
        the caller then makes the unary call. The reply's error is raised as
        the unary call's would be.
        """
        size = request.ByteSize()
        with self._lock:
            if self._closed:
                raise UnavailableError("the component is closing: no more calls")
            self._drain_call()  # the read sees the writes the gRPC call still has outstanding
            future = writes.send(request, size, False, timeout)
        if future is None:
            return None
        return reply_result(writes.wait(future))

    def _retry(self, request: wm_pb2.WriteRequest, timeout: float | None) -> wm_pb2.WriteReply:
        call, future = self._submit(request, False, timeout)
        return call.wait(future)

    def close(self, timeout: float = 2.0) -> None:
        """Stop sending; wait up to ``timeout`` for outstanding replies, then end the stream."""
        with self._lock:
            self._closed = True
            call, self._call = self._call, None
        session = self._server.shared.current() if self._server.shared is not None else None
        if session is not None:
            session.writes.drain(timeout)  # answered while the session is still open (the transport ends it)
        if call is None:
            return
        with call.lock:
            call.drain(timeout)
        call.close()
        call.pump.join(timeout)
        if call.pump.is_alive():
            call.cancel()
