"""One WorkingMemory.Write call: a component's writes and locks on one stream, each answered by id.

How requests are applied, answered and their caller checked is
:mod:`cast.server.writes`, which the shared-memory socket's WRITES frames
share (:mod:`cast.server.socket_writes`); this module is the gRPC side: it
reads the stream's messages and yields the replies.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable

from cast.core.records import Identity
from cast.core.system import System
from cast.server import socket_events
from cast.server.writes import Writes, watch_woken, woken
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["WriteStream", "watch_woken"]


class WriteStream:
    """One Write call of one component."""

    def __init__(self, system: System, caller: Callable[[], tuple[Identity, float]]) -> None:
        self._late = asyncio.Event()  # a waiting request was answered
        self._writes = Writes(system, caller, self._late.set)

    async def run(self, messages: AsyncIterator[wm_pb2.WriteRequests]) -> AsyncIterator[wm_pb2.WriteReplies]:
        """Yield the replies until the client has closed its side and every request is answered.

        While no request waits, this reads a message, applies it and sends
        its replies in one message, in one coroutine like a bare echo stream
        (each hand-off between tasks would cost an event-loop round per
        write). While some wait, it also watches for their late replies.
        Replies that are ready together go out in one message: with many
        requests in flight, the per-message cost of gRPC is shared by them.
        A message's events go out before its reply, so what watchers wait for
        does not queue behind the writer's acknowledgement (docs/performance.md,
        M8): the socket watchers' are sent before the reply is yielded
        (:mod:`cast.server.socket_events`), and when the writes woke gRPC watch
        streams, the reply waits one turn of the loop, theirs.
        """
        writes = self._writes
        source = messages.__aiter__()
        reading: asyncio.Future[wm_pb2.WriteRequests] | None = None
        try:
            while True:
                before = woken()
                if reading is None and not writes.waiting:
                    try:
                        message = await source.__anext__()
                    except StopAsyncIteration:
                        break
                    before = woken()
                    writes.apply(message.requests)
                else:
                    if reading is None:
                        reading = asyncio.ensure_future(source.__anext__())
                    late = asyncio.ensure_future(self._late.wait())
                    await asyncio.wait((reading, late), return_when=asyncio.FIRST_COMPLETED)
                    late.cancel()
                    self._late.clear()
                    if reading.done():
                        done, reading = reading, None
                        before = woken()
                        try:
                            writes.apply(done.result().requests)
                        except StopAsyncIteration:
                            break
                if writes.ready:
                    if woken() != before:
                        # Events before acknowledgements: the gRPC watch streams these writes woke are ready to
                        # run (socket ones' callbacks among them, in the order woken); one turn of the loop lets
                        # them send their events before this reply costs its send.
                        await asyncio.sleep(0)
                    socket_events.serve()  # the socket watchers' events of these writes go now, before the reply
                    yield writes.take()
            while writes.waiting:  # the client closed its side: answer what still waits, then end
                await asyncio.wait(set(writes.waiting))
                if writes.ready:
                    socket_events.serve()
                    yield writes.take()
            if writes.ready:
                socket_events.serve()
                yield writes.take()
        finally:
            if reading is not None:
                reading.cancel()
            writes.cancel()  # a lock still waiting for a client that left: give up the wait
