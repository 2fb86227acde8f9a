"""The live changes the page lists: one watch stream per server, every change of every SA, and task decisions.

The watch is the client library's :class:`WatchStream`, so a broken connection
or a restarted server is resumed from the revision after the last one received
(no gap, no duplicate). When a resume is refused (the history no longer reaches
back, or the server lost it) the feed watches again from now and lists a gap
saying so, as ``cast record`` marks one. Changes carry no values (the page asks
for the one value it shows); only ``cast.v1.Task`` changes come with their
entry, so that each task decision is listed with its state.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

from google.protobuf.message import DecodeError

from cast.client.watch_stream import WatchStream
from cast.core.records import TASK_TYPE, ChangeEvent, Operation
from cast.core.watch import EventFilter
from cast.errors import CastError
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.web.source import SystemSource

__all__ = ["KEEP_CHANGES", "KEEP_DECISIONS", "ChangeFeed", "task_json"]

KEEP_CHANGES = 200
"""How many of the latest changes the feed keeps (the page shows the last N of them)."""
KEEP_DECISIONS = 100
"""How many of the latest task decisions the feed keeps."""

# The task filter first: within one watch the first filter an event matches decides whether its entry comes along.
_FILTERS = (EventFilter(type=TASK_TYPE, include_entry=True), EventFilter())
_RETRY_S = 1.0


def _enum(name: str, prefix: str) -> str:
    return name.removeprefix(prefix).lower()


def task_json(task: tm_pb2.Task) -> dict[str, Any]:
    """A task as the page shows it (states and outcomes in lower case, times in seconds since the epoch)."""
    return {
        "task_id": task.task_id, "name": task.name, "subarchitecture": task.subarchitecture,
        "component": task.component, "priority": task.priority,
        "state": _enum(tm_pb2.TaskState.Name(task.state), "TASK_STATE_"),
        "outcome": _enum(tm_pb2.TaskOutcome.Name(task.outcome), "TASK_OUTCOME_") if task.outcome else "",
        "reason": task.reason,
        "proposed": task.proposed.ToNanoseconds() / 1e9 if task.HasField("proposed") else None,
        "decided": task.decided.ToNanoseconds() / 1e9 if task.HasField("decided") else None,
    }


class _Server:
    """One server's watch: its SAs, its stream, whether it must be created again."""

    def __init__(self, sas: list[str]) -> None:
        self.sas = sas
        self.stream: WatchStream | None = None
        self.watch_id = 0
        self.failure: CastError | None = None
        self.retry_at = 0.0


class ChangeFeed:
    """The latest changes and task decisions of every SA, each numbered in arrival order (``seq``)."""

    def __init__(self, source: SystemSource, keep: int = KEEP_CHANGES) -> None:
        self._source = source
        self._mutex = threading.Lock()
        self._closing = threading.Event()
        self._changes: deque[dict[str, Any]] = deque(maxlen=keep)
        self._decisions: deque[dict[str, Any]] = deque(maxlen=KEEP_DECISIONS)
        self._seq = 0
        self._types: dict[str, set[str]] = {}  # per SA, the types seen changing
        self._servers: list[tuple[Any, _Server]] = [(link, _Server(sas)) for link, sas in source.servers()]

    def start(self) -> None:
        """Create the watches (from now); the named error if a server refuses."""
        for link, server in self._servers:
            self._watch(link, server)

    def _watch(self, link: Any, server: _Server) -> None:
        stream = server.stream
        if stream is None or stream.dead:
            if stream is not None:
                stream.close()

            def failed(error: CastError, server: _Server = server) -> None:
                server.failure = server.failure or error  # on the stream's thread: watched again by poll()

            stream = server.stream = WatchStream(link, self._source.tokens, self._sink, failed, self._closing)
        server.watch_id += 1
        stream.create(server.watch_id, _FILTERS, {}, 10.0)

    def poll(self) -> None:
        """Watch again where a watch failed (called by the view's poller every tick)."""
        now = time.monotonic()
        for link, server in self._servers:
            if server.failure is None or now < server.retry_at:
                continue
            reason = server.failure
            try:
                self._watch(link, server)
            except CastError:
                server.retry_at = now + _RETRY_S  # the server is away again
                continue
            server.failure = None
            self._add({"gap": True, "subarchitecture": ", ".join(server.sas), "time": time.time(),
                       "reason": f"changes were missed ({reason.message}); watching again from now"})

    @property
    def connected(self) -> bool:
        """Whether every server's watch stream is connected."""
        return all(s.stream is not None and s.stream.connected and s.failure is None for _, s in self._servers)

    def _sink(self, event: ChangeEvent, _ids: Sequence[int]) -> None:
        item = {
            "revision": event.revision, "operation": event.operation.name.lower(), "subarchitecture":
            event.subarchitecture, "id": event.id, "type": event.type, "version": event.version,
            "author": event.source_component, "author_subarchitecture": event.source_subarchitecture,
            "time": event.time_ns / 1e9,
        }
        with self._mutex:
            self._types.setdefault(event.subarchitecture, set()).add(event.type)
        self._add(item)
        decided = event.operation is not Operation.DELETE  # a task entry is deleted once it is over: no decision
        if decided and event.type == TASK_TYPE and event.entry is not None and event.entry.data:
            try:
                task = task_json(tm_pb2.Task.FromString(bytes(event.entry.data)))
            except DecodeError:
                return  # not the server's task entry: the change is listed, not as a decision
            with self._mutex:
                self._decisions.append({**task, "time": event.time_ns / 1e9, "revision": event.revision})

    def _add(self, item: dict[str, Any]) -> None:
        with self._mutex:
            self._seq += 1
            self._changes.append({"seq": self._seq, **item})

    @property
    def seq(self) -> int:
        """The number of the latest change (0: none yet)."""
        return self._seq

    def since(self, seq: int) -> list[dict[str, Any]]:
        """The changes kept that came after number ``seq``, oldest first."""
        with self._mutex:
            return [c for c in self._changes if c["seq"] > seq]

    def types(self, sa: str) -> set[str]:
        """The types seen changing in an SA (the page's type filter offers them)."""
        with self._mutex:
            return set(self._types.get(sa, ()))

    def decisions(self) -> list[dict[str, Any]]:
        """The latest task decisions, newest first."""
        with self._mutex:
            return list(reversed(self._decisions))

    def close(self) -> None:
        """End the watch streams."""
        self._closing.set()
        for _, server in self._servers:
            if server.stream is not None:
                server.stream.close()
