"""Reaching working memories over gRPC: routing by SA, streams on background threads."""

from __future__ import annotations

import logging
import os
import queue
import socket
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import grpc
from google.protobuf import any_pb2, descriptor_pb2

from cast.client.connection import Backoff, ClientTls, TokenSource
from cast.client.transport import EventSink
from cast.convert import TYPE_URL_PREFIX, entry_from_pb, event_from_pb, filter_to_pb, task_from_pb
from cast.core.records import BatchOp, EntryRecord, Identity, LockMode, Operation, WriteResult
from cast.core.sessions import ComponentState
from cast.core.tasks import TaskOutcome, TaskRecord
from cast.core.watch import EventFilter
from cast.errors import CastError, DeadlineExceededError, HistoryExpiredError, UnavailableError, error_for_code
from cast.v1 import (
    directory_pb2 as dir_pb2,
)
from cast.v1 import (
    directory_pb2_grpc as dir_grpc,
)
from cast.v1 import (
    entry_pb2,
)
from cast.v1 import (
    task_manager_pb2 as tm_pb2,
)
from cast.v1 import (
    task_manager_pb2_grpc as tm_grpc,
)
from cast.v1 import (
    working_memory_pb2 as wm_pb2,
)
from cast.v1 import (
    working_memory_pb2_grpc as wm_grpc,
)

__all__ = ["GrpcTransport", "map_rpc_error"]

log = logging.getLogger("cast.client")

MAX_MESSAGE_BYTES = 64 * 1024 * 1024
CHANNEL_OPTIONS = (
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.keepalive_time_ms", 10_000),
    ("grpc.keepalive_timeout_ms", 5_000),
    ("grpc.keepalive_permit_without_calls", 1),
    # Try again soon after the server went away (gRPC's default backoff grows to two minutes),
    # so a restarted server is found within a few seconds.
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 2_000),
)

# Errors after which a stream is opened again (the server went away, or the connection broke);
# any other error ends the stream for good and is reported.
_TRANSIENT = ("UNAVAILABLE", "UNKNOWN", "INTERNAL", "CANCELLED", "DEADLINE_EXCEEDED", "UNAUTHENTICATED")


def map_rpc_error(exc: grpc.RpcError) -> CastError:
    """The named CAST error for a failed call."""
    code = exc.code() if hasattr(exc, "code") else grpc.StatusCode.UNKNOWN
    details = exc.details() if hasattr(exc, "details") else str(exc)
    name = code.name if code is not None else "UNKNOWN"
    if name == "UNAVAILABLE":
        return UnavailableError(
            f"server unavailable ({details}): a write made by this call may or may not have been applied; the "
            "client reconnects by itself, retry the call later"
        )
    return error_for_code(name, details or name)


def _any(type_name: str, data: bytes) -> any_pb2.Any:
    return any_pb2.Any(type_url=TYPE_URL_PREFIX + type_name, value=data)


def _fill_write(req: wm_pb2.AddRequest | wm_pb2.OverwriteRequest, sa: str, entry_id: str, type_name: str,
                data: bytes) -> None:
    # In place: about a third of the cost of building the nested messages and copying them in.
    req.address.id = entry_id
    req.address.subarchitecture = sa
    req.value.type_url = TYPE_URL_PREFIX + type_name
    req.value.value = data


def _addr(sa: str, entry_id: str) -> entry_pb2.EntryAddress:
    return entry_pb2.EntryAddress(id=entry_id, subarchitecture=sa)


class _Server:
    """One server endpoint: its channel and stubs."""

    def __init__(self, endpoint: str, tls: ClientTls | None = None) -> None:
        self.endpoint = endpoint
        if tls is None:
            self.channel = grpc.insecure_channel(endpoint, options=CHANNEL_OPTIONS)
        else:
            options = [*CHANNEL_OPTIONS, *tls.channel_options()]
            self.channel = grpc.secure_channel(endpoint, tls.credentials(), options=options)
        self.wm = wm_grpc.WorkingMemoryStub(self.channel)
        self.tm = tm_grpc.TaskManagerStub(self.channel)
        self.directory = dir_grpc.DirectoryStub(self.channel)
        self.watch_stream: _WatchStream | None = None
        self.session_id = ""
        self.registered = threading.Event()  # a session is open on this server
        self.beat_now = threading.Event()  # the component's state changed: send a heartbeat at once

    def close(self) -> None:
        self.channel.close()


class _Watch:
    """What the client keeps of one watch so that it can be created again after a reconnect."""

    __slots__ = ("base", "filters", "first_starts", "sas", "watch_id")

    def __init__(self, watch_id: int, filters: Sequence[EventFilter], starts: dict[str, int]) -> None:
        self.watch_id = watch_id
        self.filters = list(filters)
        self.first_starts = starts
        self.sas: list[str] = []  # the SAs of this server the watch covers (known once created)
        # Per SA, the revision the watch is known to have seen up to (None until created).
        self.base: dict[str, int] | None = None


class _WatchStream:
    """One Watch call to one server, shared by every watch of the component on that server.

    When the connection breaks the stream is opened again with backoff and every
    watch is created again from the revision after the last one it got (per SA):
    no gap and no duplicate. The server's history id comes along, so a server that
    lost that history (restarted without persistence) refuses the resume, and the
    component is told to resynchronise (``watch_failed`` with HistoryExpiredError).
    """

    def __init__(
        self,
        server: _Server,
        tokens: TokenSource,
        sink: EventSink,
        on_error: Callable[[CastError], None],
        closing: threading.Event,
    ) -> None:
        self._server = server
        self._tokens = tokens
        self._sink = sink
        self._on_error = on_error
        self._closing = closing
        self._mutex = threading.Lock()
        self._watches: dict[int, _Watch] = {}
        self._pending: dict[int, tuple[threading.Event, list[Any]]] = {}
        # The newest revision per SA received on this stream: the server moves every watch of an SA
        # on one stream past the events it sends, so each watch has seen at least this far.
        self._seen: dict[str, int] = {}
        self.history_id = ""
        self.connected = False
        self.dead = False  # ended for good (e.g. fell behind the history): a new watch needs a new stream
        self.reconnects = 0
        self._closed = False
        self._requests: queue.SimpleQueue[wm_pb2.WatchRequest | None] | None = None
        self._call: Any = None
        self._opened = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"cast-watch-{server.endpoint}", daemon=True)
        self._thread.start()
        self._opened.wait()

    # ------------------------------------------------------------ requests

    def _create_request(self, w: _Watch) -> wm_pb2.WatchRequest:
        if w.base is None:
            starts, history_id = w.first_starts, ""
        else:
            starts = {sa: max(w.base.get(sa, 0), self._seen.get(sa, 0)) + 1 for sa in w.sas}
            # What is sent is where the watch now is: a later resume never goes back before it.
            w.base = {sa: start - 1 for sa, start in starts.items()}
            history_id = self.history_id
        create = wm_pb2.WatchCreate(
            watch_id=w.watch_id, filters=[filter_to_pb(f) for f in w.filters], start_revisions=starts,
            history_id=history_id,
        )
        return wm_pb2.WatchRequest(create=create)

    def _open(self) -> Any:
        with self._mutex:
            requests: queue.SimpleQueue[wm_pb2.WatchRequest | None] = queue.SimpleQueue()
            self._requests = requests
            for w in self._watches.values():
                requests.put(self._create_request(w))
            self._call = self._server.wm.Watch(iter(requests.get, None), metadata=self._tokens.metadata())
            return self._call

    # -------------------------------------------------------------- reader

    def _run(self) -> None:
        backoff = Backoff()
        first = True
        while not self._closed:
            call = self._open()
            if first:
                self._opened.set()
                first = False
            try:
                for resp in call:
                    if not self.connected:
                        self.connected = True
                        backoff.reset()
                    self._handle(resp)
                error: CastError = UnavailableError(f"the watch stream to {self._server.endpoint} ended")
            except grpc.RpcError as exc:
                error = map_rpc_error(exc)
            self.connected = False
            if self._closed or self._closing.is_set():
                return
            if error.code not in _TRANSIENT:
                self._fail(error)
                return
            log.warning("watch stream to %s broke (%s); reconnecting", self._server.endpoint, error.message)
            self.reconnects += 1
            if self._closing.wait(backoff.next()):
                return

    def _handle(self, resp: wm_pb2.WatchResponse) -> None:
        if resp.events:
            for pb in resp.events:
                event = event_from_pb(pb)
                self._sink(event, pb.watch_ids)
                if event.revision > self._seen.get(event.subarchitecture, 0):
                    self._seen[event.subarchitecture] = event.revision
        if resp.HasField("created"):
            created = resp.created
            self.history_id = created.history_id or self.history_id
            w = self._watches.get(created.watch_id)
            if w is not None and w.base is None:
                revisions = dict(created.revisions)
                covers_all = any(not f.subarchitecture for f in w.filters)
                w.sas = [sa for sa in revisions if covers_all or any(f.subarchitecture == sa for f in w.filters)]
                w.base = {sa: w.first_starts.get(sa, revisions[sa] + 1) - 1 for sa in w.sas}
            self._resolve(created.watch_id, dict(created.revisions))
        if resp.HasField("failed"):
            failed = resp.failed
            error = error_for_code(failed.code, failed.message)
            if failed.watch_id in self._pending:
                self._resolve(failed.watch_id, error)
            elif self._watches.pop(failed.watch_id, None) is not None:
                # A resume refused after a reconnect: the history no longer covers it (or the server
                # lost it): the component must resynchronise.
                if not isinstance(error, HistoryExpiredError):
                    error = HistoryExpiredError(f"watch {failed.watch_id} could not resume: {failed.message}")
                self._on_error(error)

    def _fail(self, error: CastError) -> None:
        self.dead = True
        with self._mutex:
            self._watches.clear()
        for wid in list(self._pending):
            self._resolve(wid, error)
        self._on_error(error)

    def _resolve(self, watch_id: int, result: Any) -> None:
        pending = self._pending.pop(watch_id, None)
        if pending is not None:
            pending[1].append(result)
            pending[0].set()

    # ---------------------------------------------------------------- API

    def create(
        self, watch_id: int, filters: Sequence[EventFilter], starts: dict[str, int], timeout: float
    ) -> dict[str, int]:
        done = threading.Event()
        box: list[Any] = []
        w = _Watch(watch_id, filters, starts)
        with self._mutex:
            self._pending[watch_id] = (done, box)
            self._watches[watch_id] = w
            if self._requests is not None:
                self._requests.put(self._create_request(w))
        if not done.wait(timeout):
            self._pending.pop(watch_id, None)
            self._watches.pop(watch_id, None)
            if not self.connected:
                raise UnavailableError(
                    f"server {self._server.endpoint} unreachable: the watch was not created within {timeout} s"
                )
            raise DeadlineExceededError(f"the server did not confirm watch {watch_id} within {timeout} s")
        result = box[0]
        if isinstance(result, CastError):
            self._watches.pop(watch_id, None)
            raise result
        return dict(result)

    def cancel(self, watch_id: int) -> None:
        with self._mutex:
            self._watches.pop(watch_id, None)
            if self._requests is not None:
                self._requests.put(wm_pb2.WatchRequest(cancel=wm_pb2.WatchCancel(watch_id=watch_id)))

    def close(self) -> None:
        self._closed = True
        with self._mutex:
            if self._requests is not None:
                self._requests.put(None)
            call = self._call
        if call is not None:
            call.cancel()


class GrpcTransport:
    """A component's connection to a CAST system through its directory endpoint."""

    delivers_on_writer_thread = False

    def __init__(
        self,
        endpoint: str,
        token: str | TokenSource,
        identity: Identity,
        call_timeout: float = 30.0,
        tls: ClientTls | None = None,
    ) -> None:
        self.identity = identity
        self._tokens = token if isinstance(token, TokenSource) else TokenSource(token)
        self._tls = tls
        self._timeout = call_timeout
        self._lock = threading.Lock()
        self._directory = _Server(endpoint, tls)
        self._servers: dict[str, _Server] = {endpoint: self._directory}
        self._watch_servers: dict[int, list[_Server]] = {}
        self._sink: EventSink | None = None
        self._on_error: Callable[[CastError], None] = lambda err: log.error("watch failed: %s", err)
        self._decision_threads: list[threading.Thread] = []
        self._closing = threading.Event()
        self._routes: dict[str, _Server] = {}
        self.sessions = 0  # sessions registered (more than one per server after reconnects)
        self._describe()

    # --------------------------------------------------------------- routing

    def _call(self, fn: Callable[..., Any], request: Any, timeout: float | None = -1.0) -> Any:
        deadline = self._timeout if timeout == -1.0 else timeout
        try:
            return fn(request, metadata=self._tokens.metadata(), timeout=deadline)
        except grpc.RpcError as exc:
            error = map_rpc_error(exc)
        # A refused token may just have been renewed in its file: read it and try once more.
        if error.code == "UNAUTHENTICATED" and self._tokens.refresh():
            try:
                return fn(request, metadata=self._tokens.metadata(), timeout=deadline)
            except grpc.RpcError as exc:
                error = map_rpc_error(exc)
        raise error from None

    def _describe(self) -> dir_pb2.SystemDescription:
        desc: dir_pb2.SystemDescription = self._call(
            self._directory.directory.DescribeSystem, dir_pb2.DescribeSystemRequest()
        )
        self._system = desc
        with self._lock:
            for sa in desc.subarchitectures:
                if not sa.endpoint or sa.endpoint == desc.endpoint:
                    self._routes[sa.name] = self._directory
                else:
                    server = self._servers.get(sa.endpoint)
                    if server is None:
                        server = self._servers[sa.endpoint] = _Server(sa.endpoint, self._tls)
                    self._routes[sa.name] = server
        return desc

    def _server(self, sa: str) -> _Server:
        # An SA the directory does not know is sent to the directory's server,
        # which answers NOT_FOUND naming the SAs it knows.
        return self._routes.get(sa, self._directory)

    def system_name(self) -> str:
        """The system's name."""
        return self._system.name

    def subarchitectures(self) -> list[str]:
        """The system's SA names."""
        return [sa.name for sa in self._system.subarchitectures]

    def describe(self) -> dir_pb2.SystemDescription:
        """A fresh system description from the directory."""
        return self._describe()

    # ---------------------------------------------------------------- writes

    def add(self, sa: str, entry_id: str, type_name: str, data: bytes) -> WriteResult:
        """Create an entry."""
        req = wm_pb2.AddRequest()
        _fill_write(req, sa, entry_id, type_name, data)
        resp = self._call(self._server(sa).wm.Add, req)
        return WriteResult(resp.revision, resp.version)

    def overwrite(
        self, sa: str, entry_id: str, type_name: str, data: bytes, expected_version: int | None
    ) -> WriteResult:
        """Replace an entry's value."""
        req = wm_pb2.OverwriteRequest()
        _fill_write(req, sa, entry_id, type_name, data)
        if expected_version is not None:
            req.expected_version = expected_version
        resp = self._call(self._server(sa).wm.Overwrite, req)
        return WriteResult(resp.revision, resp.version)

    def delete(self, sa: str, entry_id: str, expected_version: int | None) -> WriteResult:
        """Delete an entry."""
        req = wm_pb2.DeleteRequest(address=_addr(sa, entry_id), expected_version=expected_version)
        resp = self._call(self._server(sa).wm.Delete, req)
        return WriteResult(resp.revision, resp.version)

    def batch(self, ops: Sequence[BatchOp]) -> list[WriteResult]:
        """Apply writes in order, all or nothing, on the server of the first operation's SA."""
        if not ops:
            return []
        # Filling the request in place is about three times cheaper than building
        # each nested message and copying it in (this is the hot loop of Batch).
        request = wm_pb2.BatchRequest()
        items = request.operations
        for op in ops:
            item = items.add()
            write: wm_pb2.AddRequest | wm_pb2.OverwriteRequest | wm_pb2.DeleteRequest
            if op.operation is Operation.ADD:
                write = item.add
            elif op.operation is Operation.OVERWRITE:
                write = item.overwrite
            else:
                write = item.delete
            if isinstance(write, wm_pb2.DeleteRequest):
                write.address.id = op.id
                write.address.subarchitecture = op.subarchitecture
            else:
                _fill_write(write, op.subarchitecture, op.id, op.type, op.data)
            if not isinstance(write, wm_pb2.AddRequest) and op.expected_version is not None:
                write.expected_version = op.expected_version
        resp = self._call(self._server(ops[0].subarchitecture).wm.Batch, request)
        return [WriteResult(r.revision, r.version) for r in resp.results]

    # ----------------------------------------------------------------- reads

    def get(self, sa: str, entry_id: str) -> EntryRecord:
        """Read one entry."""
        req = wm_pb2.GetRequest()
        req.address.id, req.address.subarchitecture = entry_id, sa
        resp = self._call(self._server(sa).wm.Get, req)
        return entry_from_pb(resp.entry)

    def get_by_type(self, sa: str, type_name: str, limit: int) -> list[EntryRecord]:
        """Read the entries of one type, newest first."""
        req = wm_pb2.GetByTypeRequest(subarchitecture=sa, type=type_name, limit=limit)
        resp = self._call(self._server(sa).wm.GetByType, req)
        return [entry_from_pb(e) for e in resp.entries]

    def exists(self, sa: str, entry_id: str) -> bool:
        """Whether an entry exists."""
        resp = self._call(self._server(sa).wm.Exists, wm_pb2.ExistsRequest(address=_addr(sa, entry_id)))
        return bool(resp.exists)

    # ----------------------------------------------------------------- locks

    def lock(self, sa: str, entry_id: str, mode: LockMode, timeout: float | None, no_wait: bool) -> int:
        """Take a lock; the wait is bounded by the call's deadline."""
        req = wm_pb2.LockRequest(address=_addr(sa, entry_id), mode=int(mode), no_wait=no_wait)  # type: ignore[arg-type]
        resp = self._call(self._server(sa).wm.Lock, req, timeout=timeout)
        return int(resp.depth)

    def unlock(self, sa: str, entry_id: str) -> int:
        """Release one level of a lock."""
        resp = self._call(self._server(sa).wm.Unlock, wm_pb2.UnlockRequest(address=_addr(sa, entry_id)))
        return int(resp.depth)

    # --------------------------------------------------------------- schemas

    def register_schemas(self, files: Sequence[descriptor_pb2.FileDescriptorProto]) -> None:
        """Register entry types with every server of the system."""
        req = dir_pb2.RegisterSchemasRequest(files=descriptor_pb2.FileDescriptorSet(file=files))
        for server in list(self._servers.values()):
            self._call(server.directory.RegisterSchemas, req)

    # -------------------------------------------------------------- watching

    def set_event_sink(
        self, sink: EventSink, on_error: Callable[[CastError], None], room: Callable[[], int] | None = None
    ) -> None:
        """Where events go (from the watch threads, in order per server).

        The watch threads may block in ``sink``: the stream then stops being
        read, and the server lets this watcher lag (bounded by its history).
        """
        self._sink = sink
        self._on_error = on_error

    def pump(self) -> None:
        """Nothing to do: the watch threads deliver as soon as the sink takes events."""

    def watch(
        self, watch_id: int, filters: Sequence[EventFilter], start_revisions: dict[str, int] | None = None
    ) -> dict[str, int]:
        """Create a watch on every server whose SAs its filters can match."""
        if self._sink is None:
            raise RuntimeError("set_event_sink must be called before watch")
        targets: list[_Server] = []
        for f in filters:
            servers = [self._server(f.subarchitecture)] if f.subarchitecture else list(self._servers.values())
            for s in servers:
                if s not in targets:
                    targets.append(s)
        revisions: dict[str, int] = {}
        for server in targets:
            with self._lock:
                if server.watch_stream is None or server.watch_stream.dead:
                    server.watch_stream = _WatchStream(server, self._tokens, self._sink, self._on_error, self._closing)
                stream = server.watch_stream
            mine = {sa: r for sa, r in (start_revisions or {}).items() if self._server(sa) is server}
            revisions.update(stream.create(watch_id, filters, mine, self._timeout))
        self._watch_servers[watch_id] = targets
        return revisions

    def cancel_watch(self, watch_id: int) -> None:
        """Remove a watch from every server it was created on."""
        for server in self._watch_servers.pop(watch_id, []):
            if server.watch_stream is not None:
                server.watch_stream.cancel(watch_id)

    # ----------------------------------------------------------------- tasks

    def propose(self, name: str, data_type: str, data: bytes, priority: int) -> TaskRecord:
        """Propose a task to the own SA's task manager."""
        req = tm_pb2.ProposeRequest(name=name, priority=priority)
        if data_type:
            req.data.CopyFrom(_any(data_type, data))
        resp = self._call(self._server(self.identity.subarchitecture).tm.Propose, req)
        return task_from_pb(resp.task)

    def retract(self, task_id: str) -> None:
        """Withdraw a task."""
        self._call(self._server(self.identity.subarchitecture).tm.Retract, tm_pb2.RetractRequest(task_id=task_id))

    def complete(self, task_id: str, outcome: TaskOutcome, reason: str) -> None:
        """Report an adopted task's outcome."""
        req = tm_pb2.CompleteRequest(task_id=task_id, outcome=int(outcome), reason=reason)  # type: ignore[arg-type]
        self._call(self._server(self.identity.subarchitecture).tm.Complete, req)

    def set_decision_sink(self, sink: Callable[[TaskRecord], None]) -> None:
        """Open the decision stream of the own SA's task manager; decisions go to ``sink``.

        The stream is opened again after a disconnect, once the session is registered again.
        """
        server = self._server(self.identity.subarchitecture)

        def read() -> None:
            backoff = Backoff()
            while not self._closing.is_set():
                call = server.tm.Decisions(tm_pb2.DecisionsRequest(), metadata=self._tokens.metadata())
                self._decision_call = call
                try:
                    for task in call:
                        backoff.reset()
                        sink(task_from_pb(task))
                except grpc.RpcError as exc:
                    if self._closing.is_set():
                        return
                    error = map_rpc_error(exc)
                    if error.code not in _TRANSIENT:
                        self._on_error(error)
                        return
                if self._closing.wait(backoff.next()):
                    return

        thread = threading.Thread(target=read, name="cast-decisions", daemon=True)
        thread.start()
        self._decision_threads.append(thread)

    # -------------------------------------------------------------- sessions

    def start_session(self, language: str, kind: str, state: Callable[[], ComponentState]) -> None:
        """Register with every server and keep the sessions alive with heartbeat streams.

        A broken session is registered again with backoff (a new session: the
        server released the locks and tasks of the old one when it ended).
        """
        for server in list(self._servers.values()):
            interval = self._register(server, language, kind)
            threading.Thread(
                target=self._heartbeat, args=(server, interval, language, kind, state), name="cast-heartbeat",
                daemon=True,
            ).start()

    def _register(self, server: _Server, language: str, kind: str) -> float:
        req = dir_pb2.RegisterRequest(language=language, kind=kind, pid=os.getpid(), host=socket.gethostname())
        resp = self._call(server.directory.Register, req)
        server.session_id = resp.session_id
        server.registered.set()
        self.sessions += 1
        return float(max(0.05, resp.lease_ms / 3000))

    def _heartbeat(
        self, server: _Server, interval: float, language: str, kind: str, state: Callable[[], ComponentState]
    ) -> None:
        backoff = Backoff()
        while not self._closing.is_set():
            session_id = server.session_id

            def beats(session_id: str = session_id, every: float = interval) -> Iterator[dir_pb2.HeartbeatRequest]:
                while True:
                    yield dir_pb2.HeartbeatRequest(session_id=session_id, state=int(state()))  # type: ignore[arg-type]
                    server.beat_now.wait(every)
                    server.beat_now.clear()
                    if self._closing.is_set():
                        return

            try:
                for _ in server.directory.Heartbeat(beats(), metadata=self._tokens.metadata()):
                    backoff.reset()
                if self._closing.is_set():
                    return
                reason = "the server ended the heartbeat stream"
            except grpc.RpcError as exc:
                if self._closing.is_set():
                    return
                reason = map_rpc_error(exc).message
            server.registered.clear()
            log.warning(
                "session with %s lost (%s): its locks and tasks are released; registering again",
                server.endpoint, reason,
            )
            while not self._closing.wait(backoff.next()):
                try:
                    interval = self._register(server, language, kind)
                    log.info("registered again with %s (session %s)", server.endpoint, server.session_id)
                    break
                except CastError as err:
                    log.info("registering with %s failed (%s); retrying", server.endpoint, err.message)

    def report_state(self) -> None:
        """Send the component's state to every server now, not at the next heartbeat."""
        for server in self._servers.values():
            server.beat_now.set()

    def close(self) -> None:
        """End sessions and streams, close channels."""
        self._closing.set()
        for server in self._servers.values():
            server.beat_now.set()
        for server in self._servers.values():
            if server.watch_stream is not None:
                server.watch_stream.close()
        call = getattr(self, "_decision_call", None)
        if call is not None:
            call.cancel()
        for server in self._servers.values():
            server.close()
