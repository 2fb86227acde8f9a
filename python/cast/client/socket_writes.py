"""A component's Write-stream requests on its shared-memory session's socket: WRITES out, REPLIES in.

docs/client-protocol.md, "Writes on the session's socket". While a component
has a session with a server on its host, :class:`cast.client.write_stream.WriteStream`
sends every request here instead of on its gRPC call: the same
``WriteRequest`` messages in WRITES frames, answered by id in REPLIES frames,
out of order when a lock waits. No gRPC message, thread or hand-off on
either side (docs/performance.md). Mirrors the C++ client's
socket_writes.cc and the server's :mod:`cast.server.socket_writes`.

Replies are read by whoever waits for one, as on the Write stream
(leader/follower): a caller waiting for its own reply reads the session's
socket itself while no other thread does (the dispatcher, reading a watch's
events there, settles it otherwise), so a sequential write costs no hand-off
to a reader thread and back. A pump thread, started by the first pipelined
request, reads for the requests nobody waits on. Every reader fails the
requests past their deadline with DeadlineExceededError and then ends the
session, since a server that answers nothing in that time is hung; the
session's end fails what is outstanding with UnavailableError ("may or may
not have been applied"), and the next write opens a new session or goes by
gRPC.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from google.protobuf.message import DecodeError

from cast.client.write_replies import Answered, Outstanding, settle, settle_replies
from cast.errors import DeadlineExceededError, UnavailableError
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire import shared_memory as wire

if TYPE_CHECKING:
    from cast.client.shm_session import ClientSession

__all__ = ["SessionWrites"]

# How long one read waits before its reader looks at the deadlines again (and lets another thread read).
_READ_SLICE_S = 0.05
# An async request sent while more requests are in flight than are held back is held back too (up to this many,
# and only if this small), and sent with those held before it once a reply comes: one frame and one wake-up of
# the server for many requests, while as many are still in flight to keep it busy (docs/performance.md,
# "Pipelined writes on the socket").
_HOLD_MAX = 64
_HOLD_BYTES = 16 << 10


def _entry(request: bytes) -> bytes:
    """One serialized ``WriteRequest`` as an entry of a WRITES frame's ``WriteRequests`` (its field 1)."""
    size = len(request)
    length = bytearray()
    while True:
        byte = size & 0x7F
        size >>= 7
        if size:
            length.append(byte | 0x80)
        else:
            length.append(byte)
            break
    return b"\x0a" + bytes(length) + request


class SessionWrites:
    """The requests of one session: sent in WRITES frames, settled by the REPLIES that name them."""

    def __init__(self, session: ClientSession) -> None:
        self._session = session
        self.endpoint = session.endpoint
        self.lock = threading.Lock()
        self.changed = threading.Condition(self.lock)  # replies settled, or the session ended
        self._pump_wake = threading.Condition(self.lock)  # a pipelined request, or the end
        self.outstanding = Outstanding()
        # Async writes answered by the thread reading now: settled once it lets go of the socket (their
        # futures' callbacks may write and wait, which would otherwise wait for that very thread).
        self.answered: Answered = []
        self.followers = 0  # threads waiting on `changed`
        self.ended = ""  # why the session ended ("" while it lives)
        self._pump: threading.Thread | None = None
        self._locks: set[int] = set()  # ids of lock requests sent, maybe still outstanding (none is held back)

    def send(self, request: wm_pb2.WriteRequest, size: int, detached: bool,
             timeout: float | None, future: Future[Any] | None = None) -> Future[wm_pb2.WriteReply] | None:
        """Send ``request`` of ``size`` bytes (its id is set here); its reply's future, or None once the session ended.

        ``detached``: nobody waits on it (the pump reads its reply). Past
        ``timeout`` s (None: none) it fails with DeadlineExceededError.
        Sends of one component are made one at a time by its write stream, so
        the frames leave in id order. ``future``: the one to settle with the
        reply (a :class:`~cast.client.write_replies.ResultFuture`), else a new one.
        """
        session = self._session
        with self.lock:
            if self.ended:
                return None
            future = self.outstanding.add(request, detached, timeout, future)
            if request.HasField("lock"):
                self._lock_outstanding()  # those answered go first
                self._locks.add(request.id)
            if detached:
                if self._pump is None:
                    self._pump = threading.Thread(target=self._run_pump, name="cast-socket-replies", daemon=True)
                    self._pump.start()
                self._pump_wake.notify()
                if size <= _HOLD_BYTES and self._hold(session):
                    # Serialised here, with its id: a small request (a large one is never held, nor serialised
                    # under the lock that readers settling replies take).
                    session.held_writes.append(_entry(request.SerializeToString()))
                    return future
        # A frame that cannot be sent ends the session, which fails this request with the others. Those held back
        # go in front of it, in its frame, so the requests leave in id order.
        session.send_write(_entry(request.SerializeToString()))
        return future

    def _hold(self, session: ClientSession) -> bool:
        """Whether a small async request is held back rather than sent now. Call with the lock held.

        Held while more requests are in flight than are held: a reply will
        come, and its reader sends what is held (:meth:`replies`, which
        answers under this lock, so no reply slips between this look and
        the request joining the held ones). Never while a lock request is
        outstanding: a lock may wait long in the server, and the requests
        behind it are answered meanwhile.
        """
        held = len(session.held_writes)
        if held >= _HOLD_MAX or self._lock_outstanding():
            return False
        return len(self.outstanding.pending) - held - 1 > held  # sent and not answered, against held

    def _lock_outstanding(self) -> bool:
        """Whether a lock request sent here is outstanding (forgets those answered). Call with the lock held."""
        if self._locks:
            pending = self.outstanding.pending
            self._locks = {i for i in self._locks if i in pending}
        return bool(self._locks)

    # ---------------------------------------------------------------- frames

    def replies(self, body: bytes) -> None:
        """A REPLIES frame (from whichever thread read it): settle the requests it answers.

        :class:`wire.ProtocolError` when it is not a ``WriteReplies``.
        """
        try:
            message = wm_pb2.WriteReplies.FromString(body)
        except DecodeError as exc:
            raise wire.ProtocolError(f"a REPLIES frame of {len(body)} bytes is not a cast.v1.WriteReplies "
                                     f"({exc})") from None
        with self.lock:
            waited, unwaited = self.outstanding.answer(message.replies)
            self.answered += unwaited
            if self.followers:
                self.changed.notify_all()  # followers whose reply this was, and drain()
        self._session.send_held()
        settle_replies(waited)

    def end(self, why: str) -> None:
        """The session ended: what is outstanding fails with UnavailableError; nothing more is sent here."""
        with self.lock:
            self.ended = why or "closed"
            left = self.outstanding.take_all()
            self.changed.notify_all()
            self._pump_wake.notify()
        for future in left:
            settle(future, None, UnavailableError(
                f"the shared-memory session with {self.endpoint} ended ({self.ended}): this write may or may not "
                "have been applied; the client reconnects by itself, retry the call later"
            ))

    # --------------------------------------------------------------- readers

    def reader_left(self) -> None:
        """A thread stopped reading the session's socket: a writer waiting for its reply reads next.

        Without it, a writer that found another thread reading would wait out
        its slice for a reply that no one reads (the reader got its own and left).
        """
        if self.followers:  # read without the lock: a follower counts itself before it looks who reads
            with self.lock:
                self.changed.notify_all()  # each looks again: one of them reads next

    def settle_answered(self) -> None:
        """Settle the async writes answered while the socket was read; called once the reader let go of it."""
        if self.answered:  # read without the lock: only a reader adds to it, and it calls this after
            with self.lock:
                answered, self.answered = self.answered, []
            settle_replies(answered)

    def wait(self, future: Future[wm_pb2.WriteReply]) -> wm_pb2.WriteReply:
        """The reply of ``future``: read the socket while nobody else does, else wait for who does."""
        self._read_for(future.done)
        return future.result()

    def drain(self, timeout: float) -> None:
        """Wait until no request is outstanding, or ``timeout`` s."""
        end = time.monotonic() + timeout
        pending = self.outstanding.pending
        self._read_for(lambda: not pending, end)

    def _read_for(self, done: Callable[[], bool], end: float | None = None) -> None:
        """Read (or wait for the thread reading) until ``done()``, the session's end, or ``end``."""
        session = self._session
        while not done() and not self.ended:
            left = _READ_SLICE_S if end is None else min(_READ_SLICE_S, end - time.monotonic())
            if left <= 0:
                return
            if not session.read_until(done, left):
                # Another thread reads (the dispatcher, the pump, another caller): it settles, then wakes us.
                with self.lock:
                    self.followers += 1  # before it looks who reads: a reader leaving now sees it and wakes it
                    try:
                        if not done() and not self.ended and session.reading:
                            self.changed.wait(left)
                    finally:
                        self.followers -= 1
            if session.dead:
                return  # its end failed what was outstanding (or fails it now, on the thread that saw it)
            self._expire()

    def _run_pump(self) -> None:
        """Read for the pipelined requests, while there are any; end with the session."""
        detached = self.outstanding.detached
        while True:
            with self.lock:
                while not self.ended and not detached:
                    self._pump_wake.wait()
                if self.ended:
                    return
            self._read_for(lambda: not detached, time.monotonic() + _READ_SLICE_S)
            self._expire()

    def _expire(self) -> None:
        """Fail the requests past their deadline; then end the session, as the Write stream ends its call."""
        now = time.monotonic()
        with self.lock:
            earliest = self.outstanding.earliest()
            if earliest is None or earliest[0] > now:
                return
            expired = self.outstanding.take_expired(now)
            self.changed.notify_all()
        for future, waited, name in expired:
            settle(future, None, DeadlineExceededError(
                f"no reply from {self.endpoint} to the {name} on the shared-memory session within {waited:g} s: it "
                "may or may not have been applied; the session was ended and the next write opens a new one"
            ))
        # A server that answers nothing in that time is hung (or the path to it is): the others fail with it.
        self._session.abandon(f"{self.endpoint} answered no write on the shared-memory session within its deadline")
