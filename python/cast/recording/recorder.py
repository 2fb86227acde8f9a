"""Recording a running system: every change of the chosen SAs, and every gap, into a :class:`RecordingWriter`.

One watch stream per server (the client library's :class:`WatchStream`), so a
broken connection or a restarted server is resumed from the revision after the
last one received, with no gap and no duplicate. On a server's host the
stream's events come as frames on a shared-memory session's socket, read by the
recorder's own dispatcher thread, as a component's do (docs/client-protocol.md,
"A watch's events on the session's socket"), and large values are lent there
rather than sent; elsewhere, or with ``CAST_SHARED_MEMORY=off``, they come on
the gRPC call. When a resume is refused (the
server's history no longer reaches back that far, or it restarted without its
history) or the recorder fell behind the history, the recorder watches again
from the server's current revision and writes a :class:`Gap` for each SA that
missed changes: the file says what is missing, and the caller is told.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import grpc

from cast.client.channel import Backoff, ServerLink, map_rpc_error
from cast.client.credentials import ClientTls, TokenSource
from cast.client.dispatcher import Dispatcher
from cast.client.shm import attach
from cast.client.watch_stream import WatchStream
from cast.core.records import ChangeEvent
from cast.core.watch import EventFilter
from cast.errors import CastError, NotFoundError
from cast.recording.channels import FORMAT_VERSION, MAX_SEQUENCE, ChannelMap, ChannelMessage, Gap
from cast.recording.info import iso
from cast.v1 import directory_pb2 as dir_pb2

__all__ = ["RECORD_ID", "MessageSink", "RecordOptions", "RecordStats", "Recorder"]

RECORD_ID = "cast-record"
"""The identity recordings are made under (a reader: a recorder writes nothing)."""

_RESYNC_RETRY_S = 1.0
_SCHEMA_ATTEMPTS = 3
BATCH_S = 0.01
"""After taking what has come, how long the recording loop lets changes gather before it takes them again.

Taking each change as it comes costs a wake-up of the loop's thread per change, and each change's
work on cold caches; at 1,000 changes/s that was about a quarter of the recorder's CPU
(docs/performance.md, "REC1: what recording costs"). The file is flushed every second anyway; a
live view shows a change at most this much later."""
_TAKE_MAX = 1000  # changes taken at once at most, between looks at the stop, the time and the connections


class MessageSink(Protocol):
    """Where :meth:`Recorder.run` puts channel messages: the MCAP file (``RecordingWriter``) or the live view."""

    def write(self, message: ChannelMessage) -> None:
        """Take one message (its channel announced first, if new)."""

    def flush_if_due(self) -> None:
        """Called between messages, so that a sink may flush on its own schedule."""


@dataclass(frozen=True)
class RecordOptions:
    """What to record: SAs (empty: every SA), entry types (empty: every type), and where to start."""

    subarchitectures: tuple[str, ...] = ()
    types: tuple[str, ...] = ()
    from_revision: int = 0  # 0: from now; else the first revision of each SA to record


@dataclass
class RecordStats:
    """What has been recorded so far (read by a status line on another thread)."""

    changes: int = 0
    data_bytes: int = 0
    per_subarchitecture: dict[str, int] = field(default_factory=dict)
    gaps: list[Gap] = field(default_factory=list)
    reconnects: int = 0
    connected: bool = True


class _Server:
    """One server the recorder watches: its link, the SAs recorded there, its watch stream."""

    def __init__(self, link: ServerLink, sas: list[str]) -> None:
        self.link = link
        self.sas = sas
        self.stream: WatchStream | None = None
        self.watch_id = 0
        self.history = ""
        self.failure: CastError | None = None  # a resynchronisation still to do, and why
        self.retry_at = 0.0


Item = tuple[_Server, ChangeEvent | CastError]


class Recorder:
    """Watches the chosen SAs of a running system and writes every change to a recording."""

    def __init__(self, endpoint: str, tokens: TokenSource, options: RecordOptions, tls: ClientTls | None = None,
                 call_timeout: float = 10.0) -> None:
        self._tokens = tokens
        self._tls = tls
        self._timeout = call_timeout
        self.options = options
        self._closing = threading.Event()
        self._queue: queue.SimpleQueue[Item] = queue.SimpleQueue()
        self._directory = ServerLink(endpoint, tls)
        self._links: dict[str, ServerLink] = {endpoint: self._directory}
        self.system = self._describe()
        known = [sa.name for sa in self.system.subarchitectures]
        chosen = list(dict.fromkeys(options.subarchitectures)) or known
        unknown = [sa for sa in chosen if sa not in known]
        if unknown:
            raise NotFoundError(f"no subarchitecture {', '.join(repr(sa) for sa in unknown)} in system "
                                f"'{self.system.name}' (known: {', '.join(known)})")
        self.subarchitectures = chosen
        self._servers: list[_Server] = []
        by_endpoint: dict[str, _Server] = {}
        for info in self.system.subarchitectures:
            if info.name not in chosen:
                continue
            address = info.endpoint if info.endpoint and info.endpoint != self.system.endpoint else endpoint
            server = by_endpoint.get(address)
            if server is None:
                link = self._links.get(address) or ServerLink(address, tls)
                self._links[address] = link
                if link.shared is None:  # shared memory with that server when on its host, opened with the watch
                    attach(link, self._tokens, self._call)
                server = by_endpoint[address] = _Server(link, [])
                self._servers.append(server)
            server.sas.append(info.name)
        # Reads the sessions' sockets, where the watches' events come on a server's host; made with the first
        # stream, so that a recorder that never starts has no thread.
        self._dispatcher: Dispatcher | None = None
        self.channels = ChannelMap(self._schema)
        self.stats = RecordStats(per_subarchitecture=dict.fromkeys(chosen, 0))
        self._last: dict[str, int] = {}  # per SA, the newest revision recorded (or known to be before the start)
        self._sequence = 0
        self._span: tuple[int, int] | None = None  # commit times of the first and last change recorded
        self.started_ns = 0
        self.stop_reason = ""

    # ----------------------------------------------------------------- calls

    def _call(self, method: Callable[..., Any], request: Any, timeout: float | None = None) -> Any:
        """``method(request)`` with the recorder's token, within ``timeout`` (default: its call timeout)."""
        return method(request, metadata=self._tokens.metadata(), timeout=self._timeout if timeout is None else timeout)

    def _describe(self) -> dir_pb2.SystemDescription:
        try:
            desc: dir_pb2.SystemDescription = self._call(self._directory.directory.DescribeSystem,
                                                         dir_pb2.DescribeSystemRequest())
        except grpc.RpcError as exc:
            raise map_rpc_error(exc) from None
        return desc

    def _schema(self, sa: str, type_name: str) -> bytes | None:
        """The serialized FileDescriptorSet of a type as registered on the SA's server; None if nobody did."""
        link = next((s.link for s in self._servers if sa in s.sas), self._directory)
        backoff = Backoff()
        for attempt in range(_SCHEMA_ATTEMPTS):
            try:
                resp = self._call(link.directory.GetSchema, dir_pb2.GetSchemaRequest(type=type_name))
                return bytes(resp.files.SerializeToString()) if resp.files.file else None
            except grpc.RpcError as exc:
                error = map_rpc_error(exc)
                if error.code == "NOT_FOUND" or attempt == _SCHEMA_ATTEMPTS - 1:
                    return None
                time.sleep(backoff.next())
        return None

    def _filters(self, sas: Sequence[str]) -> list[EventFilter]:
        types = self.options.types or ("",)
        return [EventFilter(subarchitecture=sa, type=t, include_entry=True) for sa in sas for t in types]

    # --------------------------------------------------------------- watches

    def _open_stream(self, server: _Server) -> WatchStream:
        def sink(event: ChangeEvent, _ids: Sequence[int]) -> None:
            self._queue.put((server, event))

        def failed(error: CastError) -> None:
            # Called on the stream's thread: the watch is created again on the main thread.
            self._queue.put((server, error))

        if self._dispatcher is None:
            # Its socket read once per batch, not once per frame: the changes are written in batches anyway, and
            # a wake-up per change was most of what recording took from a writer (docs/recording.md).
            self._dispatcher = Dispatcher(RECORD_ID, read_every_s=BATCH_S)
        server.link.watch_stream = WatchStream(server.link, self._tokens, sink, failed, self._closing,
                                               self._dispatcher)
        return server.link.watch_stream

    def start(self) -> None:
        """Create the watches (from ``from_revision``, or from now); the named error if the server refuses."""
        for server in self._servers:
            server.stream = self._open_stream(server)
            server.watch_id = 1
            starts = {sa: self.options.from_revision for sa in server.sas} if self.options.from_revision else {}
            revisions = server.stream.create(server.watch_id, self._filters(server.sas), starts, self._timeout)
            server.history = server.stream.history_id
            for sa in server.sas:
                self._last[sa] = starts[sa] - 1 if starts else revisions.get(sa, 0)
        self.started_ns = time.time_ns()

    def header(self) -> dict[str, str]:
        """The ``cast.recording`` metadata: what is recorded, from where, since when."""
        return {
            "format": FORMAT_VERSION,
            "system": self.system.name,
            "endpoint": self._directory.endpoint,
            "subarchitectures": ",".join(self.subarchitectures),
            "types": ",".join(self.options.types),
            "from_revision": str(self.options.from_revision),
            "start_revisions": ",".join(f"{sa}={self._last.get(sa, 0) + 1}" for sa in self.subarchitectures),
            "started": iso(self.started_ns or time.time_ns()),
        }

    def trailer(self) -> dict[str, str]:
        """The ``cast.recording.end`` metadata: when and why the recording ended, and what it holds."""
        return {
            "stopped": iso(time.time_ns()),
            "reason": self.stop_reason,
            "changes": str(self.stats.changes),
            "gaps": str(len(self.stats.gaps)),
            "last_revisions": ",".join(f"{sa}={self._last.get(sa, 0)}" for sa in self.subarchitectures),
            # The exact span of the changes: the chunk indexes' times include gap markers (recorder clock).
            "first_change_ns": str(self._span[0] if self._span else 0),
            "last_change_ns": str(self._span[1] if self._span else 0),
        }

    # ------------------------------------------------------------------ loop

    def run(self, writer: MessageSink, stop: threading.Event, until: float | None,
            on_gap: Callable[[Gap], None]) -> None:
        """Write changes as they come until ``stop`` is set or the monotonic time ``until`` passes.

        Then the streams are closed and what they had delivered is written too.
        """
        while not stop.is_set():
            now = time.monotonic()
            if until is not None and now >= until:
                self.stop_reason = self.stop_reason or "time"
                break
            wait = 0.2 if until is None else max(0.0, min(0.2, until - now))
            try:
                server, item = self._queue.get(timeout=wait)
            except queue.Empty:
                pass
            else:
                if not self._take(writer, server, item, on_gap):
                    break
                if self._queue.empty():
                    stop.wait(BATCH_S)  # the changes coming meanwhile are taken together, after it
            self._retry_resyncs(writer, on_gap)
            self._update_connection()
            writer.flush_if_due()
        self.close()
        while True:
            try:
                server, item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, ChangeEvent) and not self._handle(writer, server, item, on_gap):
                break

    def _take(self, writer: MessageSink, server: _Server, item: ChangeEvent | CastError,
              on_gap: Callable[[Gap], None]) -> bool:
        """Handle ``item`` and what is queued behind it now, up to _TAKE_MAX; False once the recording must end.

        Bounded, so that a recorder behind a flood of changes still looks at its stop and its time.
        """
        for _ in range(_TAKE_MAX):
            if not self._handle(writer, server, item, on_gap):
                return False
            try:
                server, item = self._queue.get_nowait()
            except queue.Empty:
                return True
        return self._handle(writer, server, item, on_gap)

    def _handle(self, writer: MessageSink, server: _Server, item: ChangeEvent | CastError,
                on_gap: Callable[[Gap], None]) -> bool:
        if isinstance(item, CastError):
            if server.failure is None:
                server.failure = item
                self._resync(writer, server, on_gap)
            return True
        if self._sequence >= MAX_SEQUENCE:
            self.stop_reason = f"full: {MAX_SEQUENCE} changes are the most one file numbers; start another"
            return False
        self._sequence += 1
        t = item.time_ns
        self._span = (min(self._span[0], t), max(self._span[1], t)) if self._span else (t, t)
        for message in self.channels.messages(item, self._sequence):
            writer.write(message)
            self.stats.data_bytes += len(message.data)
        self.stats.changes += 1
        self.stats.per_subarchitecture[item.subarchitecture] = (
            self.stats.per_subarchitecture.get(item.subarchitecture, 0) + 1)
        self._last[item.subarchitecture] = item.revision
        return True

    def _resync(self, writer: MessageSink, server: _Server, on_gap: Callable[[Gap], None]) -> None:
        """Watch again from the current revision and mark what was missed, or try again a little later."""
        reason = server.failure
        assert reason is not None
        stream = server.stream
        if stream is None or stream.dead:
            if stream is not None:
                stream.close()
            stream = server.stream = self._open_stream(server)
        server.watch_id += 1
        try:
            revisions = stream.create(server.watch_id, self._filters(server.sas), {}, self._timeout)
        except CastError:
            server.retry_at = time.monotonic() + _RESYNC_RETRY_S  # the server is away again
            return
        server.failure = None
        before, after = server.history, stream.history_id
        server.history = after
        for sa in server.sas:
            last, current = self._last.get(sa, 0), revisions.get(sa, 0)
            if before == after and current <= last:
                continue  # nothing happened in this SA meanwhile
            gap = Gap(sa, last, current + 1, reason.message, time.time_ns(), before, after)
            writer.write(self.channels.gap_message(gap))
            self.stats.gaps.append(gap)
            self._last[sa] = current
            on_gap(gap)

    def _retry_resyncs(self, writer: MessageSink, on_gap: Callable[[Gap], None]) -> None:
        now = time.monotonic()
        for server in self._servers:
            if server.failure is not None and now >= server.retry_at:
                self._resync(writer, server, on_gap)

    def _update_connection(self) -> None:
        streams = [s.stream for s in self._servers if s.stream is not None]
        self.stats.connected = all(s.connected for s in streams)
        self.stats.reconnects = sum(s.reconnects for s in streams)

    def close(self) -> None:
        """End the watch streams and close the connections."""
        self._closing.set()
        for server in self._servers:
            if server.stream is not None:
                server.stream.close()
        for link in self._links.values():
            link.close()
        if self._dispatcher is not None:
            self._dispatcher.stop()

