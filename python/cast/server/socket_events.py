"""Watch streams whose events go on the session's socket, served together: one write's events in one go.

docs/client-protocol.md, "A watch's events on the session's socket". Such a
stream is not a task woken for each write: the write's wake-up puts the
stream on its event loop's list of streams due (:meth:`Due.add`, on the loop
thread), and the list is served in one pass: each stream takes its pending
events and sends them as an EVENTS frame, one after the other, with no turn
of the loop between them. The write paths serve it themselves right after a
write is applied and before they send its reply (:func:`serve`), so a
write's events are on every socket watcher's socket before the writer's
acknowledgement, every time; a callback the first wake-up scheduled serves
what no write path did (writes of in-process components and of the journal's
committer, whose wake-ups come from other threads; a connection that
drained; a watch replaying its history).

Fairness: a pass sends at most one batch per stream (4,096 events or 4 MiB
of entries); a stream with more pending is served again in the next turn of
the loop, after the other work that was waiting.
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

    __slots__ = ("__weakref__", "_loop", "_scheduled", "_streams")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._streams: dict[Served, None] = {}  # an ordered set: a stream woken twice is served once
        self._scheduled = False

    def add(self, stream: Served) -> None:
        """``stream`` has events to send: serve it in this turn (a write path) or the next (a callback)."""
        self._streams[stream] = None
        if not self._scheduled:
            self._scheduled = True
            self._loop.call_soon(self._serve_later)

    def _serve_later(self) -> None:
        self._scheduled = False
        self.serve()

    def serve(self) -> None:
        """Every stream due sends its events now (one batch each); one with more pending is due again."""
        streams = self._streams
        if not streams:
            return
        self._streams = {}
        for stream in streams:
            if stream.send_events():
                self.add(stream)  # the rest after the loop's other work: a flood never starves it


_by_loop: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Due] = weakref.WeakKeyDictionary()


def due_on(loop: asyncio.AbstractEventLoop) -> Due:
    """The list of streams due on ``loop`` (made at its first socket watch)."""
    due = _by_loop.get(loop)
    if due is None:
        due = _by_loop[loop] = Due(loop)
    return due


def serve() -> None:
    """Send the events of the socket watch streams due on the running loop: what a write path calls before its reply."""
    due = _by_loop.get(asyncio.get_running_loop())
    if due is not None:
        due.serve()
