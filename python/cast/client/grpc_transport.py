"""Reaching working memories over gRPC: unary calls routed by SA; streams and sessions in their own modules.

The client library's file map is the same in Python, C++ and Java: component,
transport (the interface), grpc_transport (this), write_stream, watch_stream,
session, conversions, credentials. Writes and locks go on the Write stream;
reads, tasks and the rest are unary calls.
"""

from __future__ import annotations

import atexit
import functools
import logging
import threading
import time
import weakref
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

import grpc
from google.protobuf import descriptor_pb2

from cast.client.channel import CHANNEL_OPTIONS, JOIN_S, TRANSIENT, Backoff, LinkClosedError, ServerLink, map_rpc_error
from cast.client.conversions import address, entry_from_pb, fill_write, task_from_pb
from cast.client.credentials import ClientTls, TokenSource
from cast.client.dispatcher import Dispatcher
from cast.client.loan import Loan
from cast.client.session import Session
from cast.client.shm import attach
from cast.client.shm_session import ClientSession, Staged
from cast.client.transport import EventSink
from cast.client.watch_stream import WatchStream
from cast.client.write_replies import ResultFuture, reply_result
from cast.client.write_stream import LOCK_REPLY_MARGIN_S, WriteStream
from cast.core.records import BatchOp, EntryRecord, Identity, LockMode, Operation, WriteResult
from cast.core.sessions import ComponentState
from cast.core.tasks import TaskOutcome, TaskRecord
from cast.core.watch import EventFilter
from cast.errors import CastError, DeadlineExceededError, UnauthenticatedError, UnavailableError
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire.values import any_of

__all__ = ["CHANNEL_OPTIONS", "GrpcTransport", "map_rpc_error"]

log = logging.getLogger("cast.client")

# Deadline of one AwaitRun long-poll: how soon a stop request ends the wait for the start barrier.
_AWAIT_RUN_POLL_S = 1.0


class _Budget:
    """What is left of one call's timeout: opening the shared-memory session on the call's way spends from it.

    Without it a hung server would hold a call for the session's opening and then for the whole call timeout.
    """

    def __init__(self, timeout: float | None) -> None:
        self._end = None if timeout is None else time.monotonic() + timeout

    def left(self) -> float | None:
        """Seconds left (None: no deadline); DeadlineExceededError once none are."""
        if self._end is None:
            return None
        left = self._end - time.monotonic()
        if left <= 0:
            raise DeadlineExceededError("the call's deadline passed while opening shared memory with the server: "
                                        "nothing was sent; the server may be hung or overloaded, retry later")
        return left

    def left_for(self, staged: _Staging) -> float | None:
        """:meth:`left` for a write whose values are ``staged``: when none is, their regions are free again."""
        try:
            return self.left()
        except DeadlineExceededError:
            _unstage(staged, None)  # nothing was sent: no request can still name them
            raise


_Staging = tuple[tuple[ClientSession, Staged], ...]
"""The values of one write request staged in shared memory, and the sessions they are staged in."""

_IN_DOUBT = (UnavailableError, DeadlineExceededError)
"""A write that failed so may yet be applied: its staged bytes must stay as they are (cast.client.shm)."""


def _write_result(reply: wm_pb2.WriteReply) -> WriteResult:
    """An async write's result from its reply; the error the reply carries, raised."""
    write = reply_result(reply).write
    return WriteResult(write.revision, write.version)


def _unstage(staged: _Staging, error: BaseException | None) -> None:
    """The write is over: free its staging regions, unless its outcome is unknown."""
    for session, region in staged:
        session.unstage(region, known=not isinstance(error, _IN_DOUBT))


_OPEN: weakref.WeakSet[GrpcTransport] = weakref.WeakSet()
"""Transports not closed yet: closed at exit, while their threads can still finish (see ServerLink.track)."""


@atexit.register
def _close_open_transports() -> None:
    # Atexit handlers run before the interpreter stops daemon threads: a script that never closed its
    # client (no `with cast.connect()`) would otherwise exit with stream threads inside gRPC calls.
    for transport in list(_OPEN):
        transport.close()


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
        self._directory = ServerLink(endpoint, tls)
        self._servers: dict[str, ServerLink] = {endpoint: self._directory}
        self._attach_shared(self._directory)
        self._watch_servers: dict[int, list[ServerLink]] = {}
        self._sink: EventSink | None = None
        self._dispatcher: Dispatcher | None = None
        self._on_error: Callable[[CastError], None] = lambda err: log.error("watch failed: %s", err)
        self._closing = threading.Event()
        self._routes: dict[str, ServerLink] = {}
        self._session = Session(identity, lambda: list(self._servers.values()), self._call, self._tokens,
                                self._closing)
        _OPEN.add(self)
        self._describe()

    # --------------------------------------------------------------- routing

    def _call(
        self, fn: Callable[..., Any], request: Any, timeout: float | None = -1.0, metadata: tuple[Any, ...] = ()
    ) -> Any:
        deadline = self._timeout if timeout == -1.0 else timeout
        try:
            return fn(request, metadata=self._tokens.metadata() + metadata, timeout=deadline)
        except grpc.RpcError as exc:
            error = map_rpc_error(exc)
        except ValueError:  # gRPC's "closed channel": after close(), a clear error rather than that
            if not self._closing.is_set():
                raise
            raise LinkClosedError("the component's client is closed: no more calls") from None
        # A refused token may just have been renewed in its file: read it and try once more.
        if error.code == "UNAUTHENTICATED" and self._tokens.refresh():
            try:
                return fn(request, metadata=self._tokens.metadata() + metadata, timeout=deadline)
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
                        server = self._servers[sa.endpoint] = ServerLink(sa.endpoint, self._tls)
                        self._attach_shared(server)
                    self._routes[sa.name] = server
        return desc

    def _attach_shared(self, server: ServerLink) -> None:
        """Shared memory with ``server`` when on its host (cast.client.shm), opened when first needed."""
        attach(server, self._tokens, self._call)

    def _server(self, sa: str) -> ServerLink:
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

    def _stream(self, sa: str) -> WriteStream:
        server = self._server(sa)
        stream = server.write_stream
        if stream is None:
            with self._lock:
                if server.write_stream is None:
                    server.write_stream = WriteStream(server, self._tokens, self._timeout)
                stream = server.write_stream
        return stream

    def _write(
        self, sa: str, request: wm_pb2.WriteRequest, timeout: float | None = -1.0, staged: _Staging = ()
    ) -> wm_pb2.WriteReply:
        """One write or lock on the Write stream of ``sa``'s server (cast.client.write_stream)."""
        error: BaseException | None = None
        try:
            return self._stream(sa).call(request, self._timeout if timeout == -1.0 else timeout)
        except BaseException as exc:
            error = exc
            raise
        finally:
            _unstage(staged, error)

    def _write_async(self, sa: str, request: wm_pb2.WriteRequest, staged: _Staging,
                     budget: _Budget) -> Future[WriteResult]:
        # One future, settled by the reply's reader with the result (write_replies.ResultFuture).
        result = ResultFuture(_write_result, functools.partial(_unstage, staged))
        timeout = budget.left_for(staged)
        try:
            self._stream(sa).submit(request, timeout, result)
        except BaseException as exc:
            _unstage(staged, exc)
            raise
        return result

    def _writer_session(self, sa: str, budget: _Budget) -> ClientSession | None:
        """The shared-memory session a write to ``sa``'s server goes on, opened within ``budget``; None: bytes.

        With the token the write goes with: a renewed one opens the session the value is staged in and sent on.
        """
        link = self._server(sa).shared
        return link.session(budget.left(), self._tokens.token()) if link is not None else None

    def loan(self, sa: str, type_name: str, header: bytes, size: int) -> Loan:
        """A loan of ``size`` bytes after ``header``: in the staging area of ``sa``'s server when it can be."""
        session = self._writer_session(sa, _Budget(self._timeout))
        if session is not None and len(header) + size >= session.threshold:
            reserved = session.reserve(header, size)
            if reserved is not None:
                return Loan(sa, type_name, header, size, (session, *reserved))
        return Loan(sa, type_name, header, size)

    def _fill(
        self, req: wm_pb2.AddRequest | wm_pb2.OverwriteRequest, sa: str, entry_id: str, type_name: str,
        data: bytes | memoryview | Loan, budget: _Budget, server_sa: str = "",
    ) -> _Staging:
        """Fill a write's value: staged in shared memory when large and on the server's host, else its bytes.

        ``server_sa``: the SA whose server the request goes to, when not ``sa`` (a batch goes to its first's).
        A loan in the session the write goes on is named where it is (nothing copied).
        """
        session = self._writer_session(server_sa or sa, budget)
        staged: Staged | None = None
        if isinstance(data, Loan):
            taken = data.take(sa, session)  # its region only when it is in ``session``, which then lives
            staged, data = (taken, b"") if isinstance(taken, Staged) else (None, taken)
        if staged is None and session is not None and len(data) >= session.threshold:
            staged = session.stage(data)
        if session is None or staged is None:
            fill_write(req, sa, entry_id, type_name, data if isinstance(data, bytes) else bytes(data))
            return ()
        fill_write(req, sa, entry_id, type_name, b"")
        req.staged_value.CopyFrom(session.staged_value(staged))
        return ((session, staged),)

    def _add_request(self, sa: str, entry_id: str, type_name: str, data: bytes | Loan,
                     budget: _Budget) -> tuple[wm_pb2.WriteRequest, _Staging]:
        request = wm_pb2.WriteRequest()
        return request, self._fill(request.add, sa, entry_id, type_name, data, budget)

    def _overwrite_request(
        self, sa: str, entry_id: str, type_name: str, data: bytes | Loan, expected_version: int | None,
        budget: _Budget,
    ) -> tuple[wm_pb2.WriteRequest, _Staging]:
        request = wm_pb2.WriteRequest()
        staged = self._fill(request.overwrite, sa, entry_id, type_name, data, budget)
        if expected_version is not None:
            request.overwrite.expected_version = expected_version
        return request, staged

    def add(self, sa: str, entry_id: str, type_name: str, data: bytes | Loan) -> WriteResult:
        """Create an entry."""
        budget = _Budget(self._timeout)
        request, staged = self._add_request(sa, entry_id, type_name, data, budget)
        reply = self._write(sa, request, budget.left_for(staged), staged)
        return WriteResult(reply.write.revision, reply.write.version)

    def add_async(self, sa: str, entry_id: str, type_name: str, data: bytes | Loan) -> Future[WriteResult]:
        """Create an entry without waiting: the future of its result."""
        budget = _Budget(self._timeout)
        request, staged = self._add_request(sa, entry_id, type_name, data, budget)
        return self._write_async(sa, request, staged, budget)

    def overwrite(
        self, sa: str, entry_id: str, type_name: str, data: bytes | Loan, expected_version: int | None
    ) -> WriteResult:
        """Replace an entry's value."""
        budget = _Budget(self._timeout)
        request, staged = self._overwrite_request(sa, entry_id, type_name, data, expected_version, budget)
        reply = self._write(sa, request, budget.left_for(staged), staged)
        return WriteResult(reply.write.revision, reply.write.version)

    def overwrite_async(
        self, sa: str, entry_id: str, type_name: str, data: bytes | Loan, expected_version: int | None
    ) -> Future[WriteResult]:
        """Replace an entry's value without waiting: the future of its result."""
        budget = _Budget(self._timeout)
        request, staged = self._overwrite_request(sa, entry_id, type_name, data, expected_version, budget)
        return self._write_async(sa, request, staged, budget)

    def delete(self, sa: str, entry_id: str, expected_version: int | None) -> WriteResult:
        """Delete an entry."""
        request = wm_pb2.WriteRequest()
        request.delete.address.id, request.delete.address.subarchitecture = entry_id, sa
        if expected_version is not None:
            request.delete.expected_version = expected_version
        reply = self._write(sa, request)
        return WriteResult(reply.write.revision, reply.write.version)

    def batch(self, ops: Sequence[BatchOp]) -> list[WriteResult]:
        """Apply writes in order, all or nothing, on the server of the first operation's SA."""
        if not ops:
            return []
        # Filling the request in place is about three times cheaper than building
        # each nested message and copying it in (this is the hot loop of Batch).
        budget = _Budget(self._timeout)
        write_request = wm_pb2.WriteRequest()
        items = write_request.batch.operations
        staged: _Staging = ()
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
                staged += self._fill(write, op.subarchitecture, op.id, op.type, op.data, budget,
                                     ops[0].subarchitecture)
            if not isinstance(write, wm_pb2.AddRequest) and op.expected_version is not None:
                write.expected_version = op.expected_version
        reply = self._write(ops[0].subarchitecture, write_request, budget.left_for(staged), staged)
        return [WriteResult(r.revision, r.version) for r in reply.batch.results]

    # ----------------------------------------------------------------- reads

    def get(self, sa: str, entry_id: str) -> EntryRecord:
        """Read one entry (a large value lent by shared memory when on the server's host)."""
        server, budget = self._server(sa), _Budget(self._timeout)
        assert server.shared is not None
        with server.shared.read(budget.left(), self._tokens.token()) as call:
            if call is not None and call.session.reads:  # a session: the read goes on its socket, a frame each way
                request = wm_pb2.WriteRequest(read_call=call.number)
                request.get.address.id, request.get.address.subarchitecture = entry_id, sa
                try:
                    reply = self._stream(sa).read(call.session.writes, request, budget.left())
                except (UnauthenticatedError, UnavailableError):
                    # The session's token expired (the unary call reads the renewed one), or the session ended
                    # before the reply (a read changes nothing, so it is made again).
                    reply = None
                if reply is not None:
                    return entry_from_pb(reply.get.entry, call)
            req = wm_pb2.GetRequest()
            req.address.id, req.address.subarchitecture = entry_id, sa
            resp = self._call(server.wm.Get, req, budget.left(), call.metadata if call is not None else ())
            return entry_from_pb(resp.entry, call)

    def get_by_type(self, sa: str, type_name: str, limit: int) -> list[EntryRecord]:
        """Read the entries of one type, newest first."""
        req = wm_pb2.GetByTypeRequest(subarchitecture=sa, type=type_name, limit=limit)
        server, budget = self._server(sa), _Budget(self._timeout)
        assert server.shared is not None
        with server.shared.read(budget.left()) as call:
            resp = self._call(server.wm.GetByType, req, budget.left(), call.metadata if call is not None else ())
            return [entry_from_pb(e, call) for e in resp.entries]

    def exists(self, sa: str, entry_id: str) -> bool:
        """Whether an entry exists."""
        resp = self._call(self._server(sa).wm.Exists, wm_pb2.ExistsRequest(address=address(sa, entry_id)))
        return bool(resp.exists)

    # ----------------------------------------------------------------- locks

    def lock(self, sa: str, entry_id: str, mode: LockMode, timeout: float | None, no_wait: bool) -> int:
        """Take a lock, waiting up to ``timeout`` (None: as long as it takes) unless ``no_wait``.

        The server ends the wait itself at ``timeout`` (DEADLINE_EXCEEDED); the client gives up
        :data:`LOCK_REPLY_MARGIN_S` later, the answer's way back. A lock that does not wait has the
        call timeout, as any other call.
        """
        request = wm_pb2.WriteRequest(timeout_ms=0 if timeout is None else max(1, round(timeout * 1000)))
        request.lock.address.id, request.lock.address.subarchitecture = entry_id, sa
        request.lock.mode, request.lock.no_wait = int(mode), no_wait  # type: ignore[assignment]
        if no_wait:
            deadline: float | None = self._timeout
        else:
            deadline = None if timeout is None else timeout + LOCK_REPLY_MARGIN_S
        return int(self._write(sa, request, timeout=deadline).lock.depth)

    def unlock(self, sa: str, entry_id: str) -> int:
        """Release one level of a lock."""
        request = wm_pb2.WriteRequest()
        request.unlock.address.id, request.unlock.address.subarchitecture = entry_id, sa
        return int(self._write(sa, request).unlock.depth)

    # --------------------------------------------------------------- schemas

    def register_schemas(self, files: Sequence[descriptor_pb2.FileDescriptorProto], sa: str | None = None) -> None:
        """Register entry types with the server of ``sa`` (None: with every server of the system)."""
        req = dir_pb2.RegisterSchemasRequest(files=descriptor_pb2.FileDescriptorSet(file=files))
        for server in [self._server(sa)] if sa is not None else list(self._servers.values()):
            self._call(server.directory.RegisterSchemas, req)

    # -------------------------------------------------------------- watching

    def set_event_sink(
        self, sink: EventSink, on_error: Callable[[CastError], None], room: Callable[[], int] | None = None,
        dispatcher: Dispatcher | None = None,
    ) -> None:
        """Where events go (from the watch threads, in order per server).

        The watch threads may block in ``sink``: the stream then stops being
        read, and the server lets this watcher lag (bounded by its history).
        """
        self._sink = sink
        self._on_error = on_error
        self._dispatcher = dispatcher

    def pump(self) -> None:
        """Nothing to do: the watch threads deliver as soon as the sink takes events."""

    def watch(
        self,
        watch_id: int,
        filters: Sequence[EventFilter],
        start_revisions: dict[str, int] | None = None,
        latest: bool = False,
    ) -> dict[str, int]:
        """Create a watch on every server whose SAs its filters can match (``latest``: conflating delivery)."""
        if self._sink is None:
            raise RuntimeError("set_event_sink must be called before watch")
        targets: list[ServerLink] = []
        for f in filters:
            servers = [self._server(f.subarchitecture)] if f.subarchitecture else list(self._servers.values())
            for s in servers:
                if s not in targets:
                    targets.append(s)
        revisions: dict[str, int] = {}
        for server in targets:
            with self._lock:
                if server.watch_stream is None or server.watch_stream.dead:
                    server.watch_stream = WatchStream(
                        server, self._tokens, self._sink, self._on_error, self._closing, self._dispatcher
                    )
                stream = server.watch_stream
            mine = {sa: r for sa, r in (start_revisions or {}).items() if self._server(sa) is server}
            revisions.update(stream.create(watch_id, filters, mine, self._timeout, latest))
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
            req.data.CopyFrom(any_of(data_type, data))
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
                try:
                    call = server.open_stream(server.tm.Decisions, tm_pb2.DecisionsRequest(),
                                              metadata=self._tokens.metadata())
                except LinkClosedError:  # the transport closed since the check above
                    return
                self._decision_call = call
                try:
                    for task in call:
                        backoff.reset()
                        sink(task_from_pb(task))
                except grpc.RpcError as exc:
                    if self._closing.is_set():
                        return
                    error = map_rpc_error(exc)
                    if error.code not in TRANSIENT:
                        self._on_error(error)
                        return
                if self._closing.wait(backoff.next()):
                    return

        thread = threading.Thread(target=read, name="cast-decisions", daemon=True)
        thread.start()
        server.track(thread)

    # -------------------------------------------------------------- outcomes

    def report(self, name: str, value: float) -> None:
        """Record an outcome with the server of the own SA (``cast stats`` merges every server's)."""
        req = insp_pb2.ReportRequest(name=name, value=value)
        self._call(self._server(self.identity.subarchitecture).inspection.Report, req)

    # -------------------------------------------------------------- sessions

    def start_session(self, language: str, kind: str, state: Callable[[], ComponentState]) -> None:
        """Register with every server and keep the sessions alive (cast.client.session).

        The server's answer completes the identity: the component id and SA it
        verified from the token, and whether the component is privileged.
        """
        self._session.start(language, kind, state)
        if self._session.verified is not None:
            self.identity = self._session.verified

    @property
    def sessions(self) -> int:
        """Sessions registered so far (restarts and reconnects count)."""
        return self._session.sessions

    def report_state(self) -> None:
        """Send the component's state to every server now, not at the next heartbeat."""
        self._session.report_state()

    def await_run(self, stopping: threading.Event) -> bool:
        """Long-poll the directory's AwaitRun until the start barrier is released, or ``stopping``.

        Each call has a short deadline, so a stop request is seen within it; a
        server that is away is asked again with backoff (one restarted by
        `cast run` has no barrier any more, and answers at once).
        """
        backoff = Backoff()
        while not stopping.is_set() and not self._closing.is_set():
            try:
                self._call(self._directory.directory.AwaitRun, dir_pb2.AwaitRunRequest(), timeout=_AWAIT_RUN_POLL_S)
                return True
            except CastError as err:
                if err.code == "DEADLINE_EXCEEDED":
                    continue
                if err.code != "UNAVAILABLE":
                    raise
            stopping.wait(backoff.next())
        return False

    def close(self) -> None:
        """End sessions and streams, close channels; once (later calls return at once)."""
        if self._closing.is_set():
            return
        self._closing.set()
        _OPEN.discard(self)
        for server in self._servers.values():
            server.beat_now()
        for server in self._servers.values():
            if server.write_stream is not None:
                server.write_stream.close()
            if server.watch_stream is not None:
                server.watch_stream.close()
        call = getattr(self, "_decision_call", None)
        if call is not None:
            call.cancel()
        # The links wait for their streams' threads together, not each for its own JOIN_S.
        deadline = time.monotonic() + JOIN_S
        for server in self._servers.values():
            server.close(deadline)
