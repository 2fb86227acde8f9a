"""Watch streams whose events go on the session's socket, served without a task: a write's events before its reply.

docs/client-protocol.md, "A watch's events on the session's socket". Such a
stream is not a task woken for each write: the write's wake-up puts the
stream on its event loop's list of streams due (:meth:`Due.add`, on the loop
thread), and the stream takes its pending events and sends them as an EVENTS
frame when the list is served. The write paths serve the whole list
themselves right after a write is applied and before they send its reply
(:func:`serve`): one write's events go to every socket watcher in one pass,
with no turn of the loop between them, and are on their sockets before the
writer's acknowledgement, every time.

When a write on the Write stream or in a WRITES frame also woke watch
streams whose events go on their gRPC call (each a task that must run for
its send), the write path does not serve the list at once: each stream due
is then served by a callback of its own that its wake-up scheduled, so the
streams are served in the order they were woken, socket and gRPC ones
alike, before the reply, which waits that turn of the loop. A unary write
or Batch serves the list and replies at once, its gRPC watch streams' tasks
running in the next turn. Serving the
socket ones first there put the gRPC watchers behind them all
(docs/performance.md, M8, "Socket watchers served in one pass"). These
callbacks also serve what no write path does: writes of in-process
components and of the journal's committer, whose wake-ups come from other
threads, a connection that drained, a watch replaying its history.

Fairness: a stream sends at most one batch (4,096 events or 4 MiB of
entries) each time it is served; one with more pending is due again, served
in the next turn of the loop, after the other work that was waiting.
"""

from __future__ import annotations

import asyncio
import weakref
from typing import Protocol

__all__ = ["Due", "Served", "due_on", "serve"]


class Served(Protocol):
    """A watch stream the list serves."""

    def send_events(self) -> bool:
        """Take the pending events and send them (one batch); True if more are pending."""


class Due:
    """The streams of one event loop that have events to send, in the order they were woken."""

    __slots__ = ("__weakref__", "_loop", "_streams")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._streams: dict[Served, None] = {}  # an ordered set: a stream woken twice is served once

    def add(self, stream: Served) -> None:
        """``stream`` has events to send: served by the write path in this turn, or by its callback."""
        if stream not in self._streams:
            self._streams[stream] = None
            self._loop.call_soon(self._serve_one, stream)

    def _serve_one(self, stream: Served) -> None:
        if stream not in self._streams:
            return  # a write path served it since
        del self._streams[stream]
        if stream.send_events():
            self.add(stream)  # the rest after the loop's other work: a flood never starves it

    def serve(self) -> None:
        """Every stream due sends its events now (one batch each); one with more pending is due again."""
        streams = self._streams
        if not streams:
            return
        self._streams = {}
        for stream in streams:
            if stream.send_events():
                self.add(stream)


_by_loop: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Due] = weakref.WeakKeyDictionary()


def due_on(loop: asyncio.AbstractEventLoop) -> Due:
    """The list of streams due on ``loop`` (made at its first socket watch)."""
    due = _by_loop.get(loop)
    if due is None:
        due = _by_loop[loop] = Due(loop)
    return due


def serve() -> None:
    """Send the events of the socket watch streams due on the running loop: what a write path calls before its reply.

    The Write stream and the session's WRITES, when their writes also woke
    gRPC watch streams' tasks (:func:`cast.server.writes.woken` moved), do not
    call it at once: the streams are then served in the order they were woken,
    by their callbacks, in the turn of the loop their reply waits for. A unary
    write or Batch calls it and replies.
    """
    due = _by_loop.get(asyncio.get_running_loop())
    if due is not None:
        due.serve()
