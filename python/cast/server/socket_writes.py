"""A component's writes on its shared-memory session: WRITES frames in, REPLIES frames out.

docs/client-protocol.md, "Writes on the session's socket". A client with a
session sends its Write-stream requests (a serialized ``cast.v1.WriteRequests``)
as WRITES frames on the session's Unix socket instead of the gRPC Write
stream, and gets the replies as REPLIES frames (a serialized
``cast.v1.WriteReplies``): the same messages, the same rules
(:mod:`cast.server.writes`), applied on the server's event loop as the frame
is read, without gRPC's threads and hand-offs (docs/performance-m8.md, "Writes
on the session's socket"). The
caller is the session's: the token its HELLO carried, verified then and again
once it expires, so a session whose token expired has its writes refused
with UNAUTHENTICATED as the Write stream's are.

Fairness: a connection applies at most :data:`REQUESTS_PER_TURN` requests per
turn of the loop and reads no more while it has frames left to apply, so a
client that floods writes neither starves the loop nor the other sessions.
While more than :data:`MAX_UNSENT` bytes of frames wait for the client to read
them, its writes are held: read, not applied (:meth:`SocketWrites.hold`), so
that their replies do not grow the server's memory; the connection is still
read, up to :data:`MAX_HELD` bytes of held WRITES, so that the RELEASEs a
client sends while it is slow to read are taken at once. A server that stopped
reading instead would block a client whose thread sends a RELEASE before it
reads again, the two sockets full each way (docs/performance-m8.md, "A watcher
slow to read, and its RELEASEs").
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable

from google.protobuf.message import DecodeError

from cast.core.records import Identity
from cast.core.shared import SharedSession
from cast.core.system import System
from cast.server import socket_events
from cast.server.writes import Writes, woken
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire import shared_memory as wire

__all__ = ["MAX_HELD", "MAX_UNSENT", "REQUESTS_PER_TURN", "SocketWrites"]

REQUESTS_PER_TURN = 64
"""The most requests one connection applies before the loop turns (other sessions, gRPC calls, watch streams)."""

MAX_UNSENT = 4 << 20
"""A connection with more bytes than this waiting to be sent to its client has its writes held until they went."""

MAX_HELD = 4 << 20
"""A connection whose writes are held is not read past this many bytes of WRITES frames waiting to be applied."""


class SocketWrites:
    """The WRITES of one session: applied in order, answered by REPLIES.

    ``send`` sends a frame on the connection (in order, queued while the
    socket is full); ``pause(True)`` stops reading the connection,
    ``pause(False)`` resumes; ``session``: the connection's session, on which
    gets lend their large values. The connection calls :meth:`hold` as its
    client falls behind reading and catches up.
    """

    def __init__(self, system: System, caller: Callable[[], tuple[Identity, float]],
                 send: Callable[[bytes], bool], pause: Callable[[bool], None], session: SharedSession) -> None:
        self._loop = asyncio.get_running_loop()
        self._writes = Writes(system, caller, self._flush, session)
        self._send = send
        self._pause = pause
        self._queue: deque[wm_pb2.WriteRequest] = deque()  # requests read, not yet applied
        self._draining = False  # a turn of the loop is scheduled to apply what is queued
        self._flushing = False  # a turn of the loop is scheduled to send the replies
        self._held = False  # the client leaves too much unread: requests read wait (hold)
        self._queued_bytes = 0  # bytes of the WRITES frames read since the queue was last empty

    def received(self, body: bytes) -> None:
        """A WRITES frame: its requests are queued, applied by :meth:`apply` once the read that brought it is handled.

        A body that does not parse raises :class:`wire.ProtocolError`, before
        any of it is queued.
        """
        try:
            message = wm_pb2.WriteRequests.FromString(body)
        except DecodeError as exc:
            raise wire.ProtocolError(
                f"WRITES frame of {len(body)} bytes is not a cast.v1.WriteRequests ({exc}): nothing of it was applied"
            ) from None
        # A slice, not the container itself: upb's repeated containers have no __iter__, so iterating one goes
        # through the sequence protocol and ends in a formatted IndexError, on every frame (~15 µs cold, perf).
        self._queue.extend(message.requests[:])
        self._queued_bytes += len(body)

    def hold(self, held: bool) -> None:
        """``held``: the client leaves more than MAX_UNSENT bytes unread; its requests wait until it caught up.

        Requests read meanwhile are queued, not applied (their replies would
        only add to what waits), and the connection is read on, up to
        MAX_HELD bytes of them; ``hold(False)`` applies what waits.
        """
        if held != self._held:
            self._held = held
            self.apply()

    def apply(self) -> None:
        """Apply what the WRITES frames of one read queued: now, or in later turns of the loop behind what waits.

        The frames of one read are answered together, in one REPLIES frame: a
        client with many writes in flight sends them faster than they are
        applied, and gets one reply frame per read rather than one per request.
        While held (:meth:`hold`) nothing is applied, and the connection is
        paused once MAX_HELD bytes of frames wait.
        """
        if self._held:
            self._pause(self._queued_bytes > MAX_HELD)
        elif self._queue and not self._draining:
            self._drain()

    def _next_turn(self) -> None:
        """The turn scheduled for the requests left: applied now, unless held since (then once it caught up)."""
        self._draining = False
        self.apply()

    def _drain(self) -> None:
        """Apply up to REQUESTS_PER_TURN queued requests; the rest in the next turn, the connection paused."""
        before = woken()
        # The socket watchers' events of these writes are sent within, before their replies (cast.server.writes).
        # Taken off the queue as a list, which the compiled build would make of a generator anyway: the same
        # requests leave the queue in both builds.
        queue = self._queue
        self._writes.apply([queue.popleft() for _ in range(min(REQUESTS_PER_TURN, len(queue)))])
        if self._queue:
            self._draining = True
            self._pause(True)
            self._loop.call_soon(self._next_turn)
        else:
            self._queued_bytes = 0
            self._pause(False)
        if woken() != before:
            # Events before acknowledgements, as the Write stream: the watch streams these writes woke (gRPC
            # ones' tasks, socket ones' callbacks, in the order woken) run in this turn of the loop, the replies
            # in the next.
            if self._writes.ready:
                self._later()
        else:
            self._flush()

    def _later(self) -> None:
        if not self._flushing:
            self._flushing = True
            self._loop.call_soon(self._flush)

    def _flush(self) -> None:
        """Send the replies ready now, in one REPLIES frame (after the socket watchers' events of their writes)."""
        self._flushing = False
        if self._writes.ready:
            socket_events.serve()  # a request that waited (a lock, the journal) was applied in a task of its own
            self._send(wire.replies(self._writes.take().SerializeToString()))

    def close(self) -> None:
        """The session ended: nothing more is applied, and requests still waiting give up."""
        self._queue.clear()
        self._queued_bytes = 0
        self._writes.cancel()
