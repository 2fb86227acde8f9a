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
(docs/performance-m8.md, "Socket watchers served in one pass"). These
callbacks also serve what no write path does: writes of in-process
components and of the journal's committer, whose wake-ups come from other
threads, a connection that drained, a watch replaying its history.

While a write path applies its writes (:meth:`Due.hold`), a socket stream
woken gets no callback yet: the write path serves the list itself right
after, so such callbacks would only find their streams served. Those woken
before a gRPC watch stream's task in the same writes get theirs at that
moment (:func:`before_task_woken`), and the rest when the write path ends
without serving them, so the order of service is the order woken all the same.

Fairness: a stream sends at most one batch (4,096 events or 4 MiB of
entries) each time it is served; one with more pending is due again, served
in the next turn of the loop, after the other work that was waiting.
"""

from __future__ import annotations

import asyncio
import weakref
from typing import Protocol

__all__ = ["Due", "Served", "before_task_woken", "due_on", "serve"]


class Served(Protocol):
    """A watch stream the list serves."""

    def send_events(self) -> bool:
        """Take the pending events and send them (one batch); True if more are pending."""


class Due:
    """The streams of one event loop that have events to send, in the order they were woken."""

    __slots__ = ("__weakref__", "_held", "_loop", "_streams", "_unscheduled")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._streams: dict[Served, None] = {}  # an ordered set: a stream woken twice is served once
        self._held = 0  # write paths applying writes now (hold): streams woken get no callback yet
        self._unscheduled: list[Served] = []  # woken while held, no callback yet, in the order woken

    def add(self, stream: Served) -> None:
        """``stream`` has events to send: served by the write path in this turn, or by its callback."""
        if stream not in self._streams:
            self._streams[stream] = None
            if self._held:
                self._unscheduled.append(stream)
            else:
                self._loop.call_soon(self._serve_one, stream)

    def hold(self) -> None:
        """A write path applies writes now: the socket streams they wake get no callback yet (:meth:`release`).

        The write path then calls :meth:`serve`, or lets the loop turn first
        (when its writes woke gRPC watch streams' tasks). Nothing may wait
        between ``hold`` and ``release``.
        """
        self._held += 1

    def release(self) -> None:
        """The write path is done: each stream woken meanwhile and not served gets its callback, in order."""
        self._held -= 1
        if not self._held and self._unscheduled:
            self.schedule()

    def schedule(self) -> None:
        """Each stream woken while held and not served since gets its callback now, in the order woken."""
        unscheduled, self._unscheduled = self._unscheduled, []
        streams = self._streams
        for stream in unscheduled:
            if stream in streams:
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
        self._unscheduled = []  # every one of them is served here
        for stream in streams:
            if stream.send_events():
                self.add(stream)


_by_loop: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Due] = weakref.WeakKeyDictionary()
# The last loop looked up and its list: a server has one loop, and WeakKeyDictionary.get is Python code run on
# every write (its Due holds the loop already, so this keeps nothing alive that the dictionary does not).
_recent: tuple[asyncio.AbstractEventLoop, Due] | None = None


def _known(loop: asyncio.AbstractEventLoop) -> Due | None:
    """The list of streams due on ``loop`` if it has one: the last one looked up first."""
    recent = _recent
    return recent[1] if recent is not None and recent[0] is loop else _by_loop.get(loop)


def due_on(loop: asyncio.AbstractEventLoop) -> Due:
    """The list of streams due on ``loop`` (made at its first socket watch or write path)."""
    global _recent
    due = _known(loop)
    if due is None:
        due = _by_loop[loop] = Due(loop)
    _recent = (loop, due)
    return due


def serve() -> None:
    """Send the events of the socket watch streams due on the running loop: what a unary write calls before its reply.

    A unary write or Batch calls it and replies. The Write stream and the
    session's WRITES hold their loop's list while they apply writes and serve
    it themselves (:meth:`Due.hold`, :meth:`Due.serve`); when their writes
    also woke gRPC watch streams' tasks (:func:`cast.server.writes.woken`
    moved), they do not serve it at once: the streams are then served in the
    order they were woken, by their callbacks, in the turn of the loop their
    reply waits for.
    """
    due = _known(asyncio.get_running_loop())
    if due is not None:
        due.serve()


def before_task_woken(due: Due) -> None:
    """A gRPC watch stream's task is about to be woken on ``due``'s loop: streams woken before it go first.

    While a write path holds the list (:meth:`Due.hold`), the socket streams
    woken so far get their callbacks now, ahead of the task, as they would
    have at their wake-up.
    """
    if due._held:
        due.schedule()
