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

from cast.client.transport import EventSink
from cast.convert import TYPE_URL_PREFIX, entry_from_pb, event_from_pb, filter_to_pb, task_from_pb
from cast.core.host import BatchOp
from cast.core.records import EntryRecord, Identity, LockMode, Operation, WriteResult
from cast.core.sessions import ComponentState
from cast.core.tasks import TaskOutcome, TaskRecord
from cast.core.watch import EventFilter
from cast.errors import CastError, DeadlineExceededError, UnavailableError, error_for_code
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
)


def map_rpc_error(exc: grpc.RpcError) -> CastError:
    """The named CAST error for a failed call."""
    code = exc.code() if hasattr(exc, "code") else grpc.StatusCode.UNKNOWN
    details = exc.details() if hasattr(exc, "details") else str(exc)
    name = code.name if code is not None else "UNKNOWN"
    if name == "UNAVAILABLE":
        return UnavailableError(f"server unavailable: {details}")
    return error_for_code(name, details or name)


def _any(type_name: str, data: bytes) -> any_pb2.Any:
    return any_pb2.Any(type_url=TYPE_URL_PREFIX + type_name, value=data)


def _addr(sa: str, entry_id: str) -> entry_pb2.EntryAddress:
    return entry_pb2.EntryAddress(id=entry_id, subarchitecture=sa)


class _Server:
    """One server endpoint: its channel and stubs."""

    def __init__(self, endpoint: str) -> None:
        self.endpoint = endpoint
        self.channel = grpc.insecure_channel(endpoint, options=CHANNEL_OPTIONS)
        self.wm = wm_grpc.WorkingMemoryStub(self.channel)
        self.tm = tm_grpc.TaskManagerStub(self.channel)
        self.directory = dir_grpc.DirectoryStub(self.channel)
        self.watch_stream: _WatchStream | None = None
        self.session_id = ""

    def close(self) -> None:
        self.channel.close()


class _WatchStream:
    """One Watch call to one server, shared by every watch of the component on that server."""

    def __init__(self, server: _Server, metadata: Any, sink: EventSink, on_error: Callable[[CastError], None]) -> None:
        self._requests: queue.SimpleQueue[wm_pb2.WatchRequest | None] = queue.SimpleQueue()
        self._pending: dict[int, tuple[threading.Event, list[Any]]] = {}
        self._sink = sink
        self._on_error = on_error
        self._closed = False
        self._call = server.wm.Watch(iter(self._requests.get, None), metadata=metadata)
        self._thread = threading.Thread(target=self._read, name=f"cast-watch-{server.endpoint}", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for resp in self._call:
                if resp.events:
                    for pb in resp.events:
                        self._sink(event_from_pb(pb), pb.watch_ids)
                if resp.HasField("created"):
                    self._resolve(resp.created.watch_id, dict(resp.created.revisions))
                if resp.HasField("failed"):
                    self._resolve(resp.failed.watch_id, error_for_code(resp.failed.code, resp.failed.message))
        except grpc.RpcError as exc:
            if self._closed:
                return
            err = map_rpc_error(exc)
            for wid in list(self._pending):
                self._resolve(wid, err)
            self._on_error(err)

    def _resolve(self, watch_id: int, result: Any) -> None:
        pending = self._pending.pop(watch_id, None)
        if pending is not None:
            pending[1].append(result)
            pending[0].set()

    def create(
        self, watch_id: int, filters: Sequence[EventFilter], starts: dict[str, int], timeout: float
    ) -> dict[str, int]:
        done = threading.Event()
        box: list[Any] = []
        self._pending[watch_id] = (done, box)
        create = wm_pb2.WatchCreate(
            watch_id=watch_id, filters=[filter_to_pb(f) for f in filters], start_revisions=starts
        )
        self._requests.put(wm_pb2.WatchRequest(create=create))
        if not done.wait(timeout):
            self._pending.pop(watch_id, None)
            raise DeadlineExceededError(f"the server did not confirm watch {watch_id} within {timeout} s")
        result = box[0]
        if isinstance(result, CastError):
            raise result
        return dict(result)

    def cancel(self, watch_id: int) -> None:
        self._requests.put(wm_pb2.WatchRequest(cancel=wm_pb2.WatchCancel(watch_id=watch_id)))

    def close(self) -> None:
        self._closed = True
        self._requests.put(None)
        self._call.cancel()  # type: ignore[no-untyped-call]


class GrpcTransport:
    """A component's connection to a CAST system through its directory endpoint."""

    delivers_on_writer_thread = False

    def __init__(self, endpoint: str, token: str, identity: Identity, call_timeout: float = 30.0) -> None:
        self.identity = identity
        self._metadata = (("authorization", f"Bearer {token}"),)
        self._timeout = call_timeout
        self._lock = threading.Lock()
        self._directory = _Server(endpoint)
        self._servers: dict[str, _Server] = {endpoint: self._directory}
        self._watch_servers: dict[int, list[_Server]] = {}
        self._sink: EventSink | None = None
        self._on_error: Callable[[CastError], None] = lambda err: log.error("watch failed: %s", err)
        self._decision_threads: list[threading.Thread] = []
        self._closing = threading.Event()
        self._routes: dict[str, _Server] = {}
        self._describe()

    # --------------------------------------------------------------- routing

    def _call(self, fn: Callable[..., Any], request: Any, timeout: float | None = -1.0) -> Any:
        try:
            return fn(request, metadata=self._metadata, timeout=self._timeout if timeout == -1.0 else timeout)
        except grpc.RpcError as exc:
            raise map_rpc_error(exc) from None

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
                        server = self._servers[sa.endpoint] = _Server(sa.endpoint)
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
        req = wm_pb2.AddRequest(address=_addr(sa, entry_id), value=_any(type_name, data))
        resp = self._call(self._server(sa).wm.Add, req)
        return WriteResult(resp.revision, resp.version)

    def overwrite(
        self, sa: str, entry_id: str, type_name: str, data: bytes, expected_version: int | None
    ) -> WriteResult:
        """Replace an entry's value."""
        req = wm_pb2.OverwriteRequest(
            address=_addr(sa, entry_id), value=_any(type_name, data), expected_version=expected_version
        )
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
        items = []
        for op in ops:
            addr = _addr(op.subarchitecture, op.id)
            if op.operation is Operation.ADD:
                items.append(wm_pb2.BatchOperation(add=wm_pb2.AddRequest(address=addr, value=_any(op.type, op.data))))
            elif op.operation is Operation.OVERWRITE:
                req = wm_pb2.OverwriteRequest(
                    address=addr, value=_any(op.type, op.data), expected_version=op.expected_version
                )
                items.append(wm_pb2.BatchOperation(overwrite=req))
            else:
                dreq = wm_pb2.DeleteRequest(address=addr, expected_version=op.expected_version)
                items.append(wm_pb2.BatchOperation(delete=dreq))
        resp = self._call(self._server(ops[0].subarchitecture).wm.Batch, wm_pb2.BatchRequest(operations=items))
        return [WriteResult(r.revision, r.version) for r in resp.results]

    # ----------------------------------------------------------------- reads

    def get(self, sa: str, entry_id: str) -> EntryRecord:
        """Read one entry."""
        resp = self._call(self._server(sa).wm.Get, wm_pb2.GetRequest(address=_addr(sa, entry_id)))
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
                if server.watch_stream is None:
                    server.watch_stream = _WatchStream(server, self._metadata, self._sink, self._on_error)
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
        """Open the decision stream of the own SA's task manager; decisions go to ``sink``."""
        server = self._server(self.identity.subarchitecture)
        call = server.tm.Decisions(tm_pb2.DecisionsRequest(), metadata=self._metadata)

        def read() -> None:
            try:
                for task in call:
                    sink(task_from_pb(task))
            except grpc.RpcError as exc:
                if not self._closing.is_set():
                    self._on_error(map_rpc_error(exc))

        self._decision_call = call
        thread = threading.Thread(target=read, name="cast-decisions", daemon=True)
        thread.start()
        self._decision_threads.append(thread)

    # -------------------------------------------------------------- sessions

    def start_session(self, language: str, kind: str, state: Callable[[], ComponentState]) -> None:
        """Register with every server and keep the sessions alive with heartbeat streams."""
        for server in list(self._servers.values()):
            req = dir_pb2.RegisterRequest(language=language, kind=kind, pid=os.getpid(), host=socket.gethostname())
            resp = self._call(server.directory.Register, req)
            server.session_id = resp.session_id
            interval = max(0.05, resp.lease_ms / 3000)
            threading.Thread(
                target=self._heartbeat, args=(server, interval, state), name="cast-heartbeat", daemon=True
            ).start()

    def _heartbeat(self, server: _Server, interval: float, state: Callable[[], ComponentState]) -> None:
        def beats() -> Iterator[dir_pb2.HeartbeatRequest]:
            while True:
                yield dir_pb2.HeartbeatRequest(session_id=server.session_id, state=int(state()))  # type: ignore[arg-type]
                if self._closing.wait(interval):
                    return

        try:
            for _ in server.directory.Heartbeat(beats(), metadata=self._metadata):
                pass
        except grpc.RpcError as exc:
            if not self._closing.is_set():
                log.error("heartbeat to %s failed: %s", server.endpoint, map_rpc_error(exc))

    def close(self) -> None:
        """End sessions and streams, close channels."""
        self._closing.set()
        for server in self._servers.values():
            if server.watch_stream is not None:
                server.watch_stream.close()
        call = getattr(self, "_decision_call", None)
        if call is not None:
            call.cancel()
        for server in self._servers.values():
            server.close()
