"""The WorkingMemory servicer: translates cast.v1 requests into calls on the core."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator

import grpc

from cast.core.access import Access, run_async
from cast.core.records import BatchOp, Identity
from cast.core.shared import SharedSession
from cast.core.system import System
from cast.core.watch import Match, Subscription
from cast.errors import CastError, InvalidArgumentError, UnavailableError
from cast.server import socket_events
from cast.server.conversions import BY_REFERENCE, fill_entry, filter_from_pb, watch_events_wire
from cast.server.rpc import Authenticator, Context, Servicer, rpc, stream_rpc
from cast.server.shared_socket import lend, read_session
from cast.server.socket_writes import MAX_UNSENT
from cast.server.write_requests import batch_ops, lock_mode, write_op
from cast.server.write_stream import WriteStream
from cast.server.writes import watch_woken
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.v1 import working_memory_pb2_grpc as wm_grpc
from cast.wire import shared_memory as wire

__all__ = ["WorkingMemoryServicer", "add_to_server"]

EVENTS_METADATA_KEY = "cast-watch-events"
"""Call metadata: ``socket`` asks for the call's event batches as EVENTS frames on the session's socket."""

EVENTS_UNSENT = MAX_UNSENT
"""A watch whose session's connection has more bytes than this unsent takes no more events until they went.

The connection's own bound for what its client leaves unread: a client whose
standby reader is held up (the GIL, two busy cores) keeps a few large values'
worth of slack before its watch lags on the server."""

# One watch batch stops growing past this many events or entry bytes, so a
# stream catching up never sends a message the client refuses for its size.
_BATCH_EVENTS = 4096
_BATCH_BYTES = 4 * 1024 * 1024


class WorkingMemoryServicer(Servicer, wm_grpc.WorkingMemoryServicer):
    """Serves every WM of one :class:`System`: translates requests to the caller's :class:`Access`."""

    SERVICE = "cast.v1.WorkingMemory"

    def __init__(self, system: System, auth: Authenticator) -> None:
        self._system = system
        self.auth = auth

    async def _write(self, access: Access, op: BatchOp) -> wm_pb2.WriteResponse:
        result = await run_async(self._system, access.write(op))
        socket_events.serve()  # the socket watchers' events of this write go before its reply
        return wm_pb2.WriteResponse(revision=result.revision, version=result.version)

    @rpc
    async def Add(self, request: wm_pb2.AddRequest, context: Context, who: Identity) -> wm_pb2.WriteResponse:
        """Create an entry."""
        access = Access(self._system, who)
        return await self._write(access, write_op(request, access))

    @rpc
    async def Overwrite(
        self, request: wm_pb2.OverwriteRequest, context: Context, who: Identity
    ) -> wm_pb2.WriteResponse:
        """Replace an entry's value."""
        access = Access(self._system, who)
        return await self._write(access, write_op(request, access))

    @rpc
    async def Delete(self, request: wm_pb2.DeleteRequest, context: Context, who: Identity) -> wm_pb2.WriteResponse:
        """Delete an entry."""
        return await self._write(Access(self._system, who), write_op(request))

    @rpc
    async def Get(self, request: wm_pb2.GetRequest, context: Context, who: Identity) -> wm_pb2.GetResponse:
        """Read one entry (its value lent by reference to a caller on this host that asks: cast.core.shared)."""
        access = Access(self._system, who)
        read = read_session(access, context)
        record = access.get(request.address.subarchitecture, request.address.id)
        response = wm_pb2.GetResponse()
        fill_entry(response.entry, record, lend(access, read, record.shared))
        return response

    @rpc
    async def GetByType(
        self, request: wm_pb2.GetByTypeRequest, context: Context, who: Identity
    ) -> wm_pb2.GetByTypeResponse:
        """Read the entries of one type, newest first."""
        access = Access(self._system, who)
        read = read_session(access, context)
        records, revision = access.get_by_type(request.subarchitecture, request.type, request.limit)
        response = wm_pb2.GetByTypeResponse(revision=revision)
        entries = response.entries
        for record in records:
            fill_entry(entries.add(), record, lend(access, read, record.shared))
        return response

    @rpc
    async def Exists(self, request: wm_pb2.ExistsRequest, context: Context, who: Identity) -> wm_pb2.ExistsResponse:
        """Whether an entry exists."""
        address = request.address
        exists = Access(self._system, who).exists(address.subarchitecture, address.id)
        return wm_pb2.ExistsResponse(exists=exists)

    @rpc
    async def Lock(self, request: wm_pb2.LockRequest, context: Context, who: Identity) -> wm_pb2.LockResponse:
        """Take a lock, waiting up to the call's deadline unless no_wait."""
        steps = Access(self._system, who).lock(
            request.address.subarchitecture, request.address.id, lock_mode(request.mode), request.no_wait
        )
        return wm_pb2.LockResponse(depth=await run_async(self._system, steps, context.time_remaining()))

    @rpc
    async def Unlock(self, request: wm_pb2.UnlockRequest, context: Context, who: Identity) -> wm_pb2.UnlockResponse:
        """Release one level of the caller's lock."""
        steps = Access(self._system, who).unlock(request.address.subarchitecture, request.address.id)
        return wm_pb2.UnlockResponse(depth=await run_async(self._system, steps))

    @rpc
    async def Batch(self, request: wm_pb2.BatchRequest, context: Context, who: Identity) -> wm_pb2.BatchResponse:
        """Apply many writes in order, all or nothing."""
        access = Access(self._system, who)
        ops = batch_ops(request, access)
        results = await run_async(self._system, access.batch(ops))
        socket_events.serve()
        response = wm_pb2.BatchResponse()
        add_result = response.results.add
        for r in results:
            add_result(revision=r.revision, version=r.version)
        return response

    @stream_rpc
    async def Write(
        self, request_iterator: AsyncIterator[wm_pb2.WriteRequests], context: Context, who: Identity
    ) -> AsyncIterator[wm_pb2.WriteReplies]:
        """Apply a component's writes and locks as they arrive on the stream, answering each by id.

        A missing or bad token ends the call at once, as every RPC does; it is
        checked again for each request, since the stream outlives tokens
        (:class:`WriteStream` says how).
        """
        stream = WriteStream(self._system, lambda: self.who_until("Write", context))
        async for reply in stream.run(request_iterator):
            yield reply

    @stream_rpc
    async def Watch(  # type: ignore[override]  # yields bytes too: see add_to_server
        self, request_iterator: AsyncIterator[wm_pb2.WatchRequest], context: Context, who: Identity
    ) -> AsyncIterator[wm_pb2.WatchResponse | bytes]:
        """Stream event batches for the watches the client creates on this stream.

        Event batches are yielded already encoded (bytes); :func:`add_to_server`
        registers a serializer that passes them through.
        """
        access = Access(self._system, who)
        read = read_session(access, context)
        on_socket = read is not None and (EVENTS_METADATA_KEY, "socket") in (context.invocation_metadata() or ())
        stream = _WatchStream(access, read, on_socket)
        try:
            async for response in stream.run(request_iterator):
                yield response
        finally:
            stream.close()


class _WatchStream:
    """One Watch call: reads create/cancel requests, writes control messages and event batches."""

    def __init__(self, access: Access, read: tuple[SharedSession, int] | None = None, on_socket: bool = False) -> None:
        self._access = access
        self._lending = read  # the caller's shared-memory session and call: values lent by reference
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._wake = asyncio.Event()
        self._control: list[wm_pb2.WatchResponse] = []
        self._error: BaseException | None = None
        self._done = False
        self._sending = False  # an event batch is being sent on the call (the client may not be reading)
        self._closed = False
        # With on_socket, event batches go as EVENTS frames on the session's connection (created, failed,
        # cancelled and the call's end stay on the call): docs/client-protocol.md. Such a stream's events are
        # sent by its loop's list of streams due (cast.server.socket_events), not by its task. Set before the
        # subscription, whose wake-ups may come at once from another thread.
        self._link = read[0].link if read is not None and on_socket else None
        self._due = socket_events.due_on(self._loop) if self._link is not None else None
        # A gRPC stream's wake-up on the loop first gives the socket streams woken before it their turn
        # (socket_events.before_task_woken): the order of service stays the order woken.
        self._loop_due = socket_events.due_on(self._loop)
        self._sub = Subscription(access.system.host, self._notify)
        self._unlisten = self._link.listen(self._link_changed) if self._link is not None else None

    def _notify(self) -> None:
        # Writes made by in-process components arrive on their own threads.
        if threading.get_ident() == self._loop_thread:
            if self._due is not None:
                self._due.add(self)  # sent before the write's reply, by the write path (socket_events)
            else:
                socket_events.before_task_woken(self._loop_due)
                self._woken()
                watch_woken()
        elif self._due is not None:
            self._loop.call_soon_threadsafe(self._due.add, self)
        else:
            self._loop.call_soon_threadsafe(self._woken)

    def _woken(self) -> None:
        self._wake.set()
        if self._sending and self._sub.has_latest:
            # The call is busy sending (its client reads slowly or not at all): latest watches keep the
            # newest change per entry meanwhile rather than their place in the history, which they would
            # lose (cast.core.watch.Subscription.hold_latest).
            self._sub.hold_latest()

    def _link_changed(self) -> None:
        """The session's connection closed (the task ends the call) or sent what waited (events may go again)."""
        assert self._link is not None and self._due is not None
        if self._link.closed:
            self._wake.set()
        else:
            self._due.add(self)

    def send_events(self) -> bool:
        """A socket watch: send the pending events as one EVENTS frame; True if more are pending.

        Runs on the loop, called by :class:`cast.server.socket_events.Due`.
        What ends the call (the connection closed, the watch fell behind the
        history, a bug) wakes the task, which ends it.
        """
        link = self._link
        assert link is not None and self._lending is not None
        if self._closed or self._error is not None:
            return False
        if link.closed:
            self._wake.set()
            return False
        if link.unsent > EVENTS_UNSENT:
            # The client is not reading: its events wait here (and lag) until those went (_link_changed), but
            # for its latest watches the newest change per entry is held (as in _woken).
            self._sub.hold_latest()
            return False
        try:
            # The history holds only visible writes, so these are durable (cast.core.host).
            matches = self._access.take(self._sub, _BATCH_EVENTS, _BATCH_BYTES)
            if not matches:
                return False
            link.send(wire.events(self._lending[1], self._events(matches)))
        except Exception as exc:  # noqa: BLE001 - OUT_OF_RANGE for a watch behind the history, or a bug: ends the call
            self._error = exc
            self._wake.set()
            return False
        return len(matches) >= _BATCH_EVENTS or self._sub.behind

    async def _read(self, requests: AsyncIterator[wm_pb2.WatchRequest]) -> None:
        try:
            async for req in requests:
                kind = req.WhichOneof("request")
                if kind == "create":
                    self._control.append(self._create(req.create))
                elif kind == "cancel":
                    if self._sub.cancel(req.cancel.watch_id):
                        self._control.append(wm_pb2.WatchResponse(cancelled=[req.cancel.watch_id]))
                else:
                    raise InvalidArgumentError("empty watch request: set create or cancel")
                self._wake.set()
        except Exception as exc:  # noqa: BLE001 - handed to the writer, which ends the call with it
            self._error = exc
        self._done = True
        self._wake.set()

    def _create(self, create: wm_pb2.WatchCreate) -> wm_pb2.WatchResponse:
        try:
            filters = [filter_from_pb(f) for f in create.filters]
            revisions = self._access.watch(
                self._sub, create.watch_id, filters, dict(create.start_revisions), create.history_id,
                latest=create.delivery == wm_pb2.DELIVERY_LATEST,
            )
        except CastError as exc:
            failed = wm_pb2.WatchFailed(watch_id=create.watch_id, code=exc.code, message=exc.message)
            return wm_pb2.WatchResponse(failed=failed)
        created = wm_pb2.WatchCreated(
            watch_id=create.watch_id, revisions=revisions, history_id=self._access.system.history_id
        )
        return wm_pb2.WatchResponse(created=created)

    async def run(self, requests: AsyncIterator[wm_pb2.WatchRequest]) -> AsyncIterator[wm_pb2.WatchResponse | bytes]:
        reader = asyncio.ensure_future(self._read(requests))
        link = self._link
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                while self._control:
                    yield self._control.pop(0)
                if self._error is not None:
                    raise self._error
                if link is not None:
                    # Its events go by send_events; this task carries the call's control messages and its end.
                    if link.closed:
                        raise UnavailableError(
                            "the shared-memory session carrying this watch's events ended: open the watch again "
                            "(it resumes after the last event received)"
                        )
                    if self._done and not self._sub.watch_ids:
                        return
                    continue
                # The history holds only visible writes, so these are durable (cast.core.host).
                matches = self._access.take(self._sub, _BATCH_EVENTS, _BATCH_BYTES)
                if matches:
                    if len(matches) >= _BATCH_EVENTS or self._sub.behind:
                        self._wake.set()  # more is pending: go round again after this batch
                    self._sending = True
                    try:
                        yield self._events(matches)
                    finally:
                        self._sending = False
                elif self._done and not self._sub.watch_ids:
                    return
        finally:
            reader.cancel()

    def _events(self, matches: list[Match]) -> bytes:
        """The batch as an encoded WatchResponse (see :func:`cast.convert.watch_events_wire`).

        With a shared-memory session, an entry whose value is in shared memory
        goes by reference, lent to the session, while its window allows.
        """
        access = self._access
        carries = access.carries_entry
        read = self._lending
        if read is None:
            return watch_events_wire([(m.event, m.watch_ids, carries(m), m.skipped, m.first_skipped) for m in matches])
        events = []
        for m in matches:
            include: int = carries(m)
            entry = m.event.entry
            if include and entry is not None and entry.shared is not None and lend(access, read, entry.shared):
                include = BY_REFERENCE
            events.append((m.event, m.watch_ids, include, m.skipped, m.first_skipped))
        return watch_events_wire(events)

    def close(self) -> None:
        self._closed = True
        self._sub.close()
        if self._unlisten is not None:
            self._unlisten()


def _serialize_watch(response: wm_pb2.WatchResponse | bytes) -> bytes:
    return response if isinstance(response, bytes) else response.SerializeToString()


def add_to_server(servicer: WorkingMemoryServicer, server: grpc.aio.Server) -> None:
    """Register the servicer like the generated helper does, but let Watch send pre-encoded batches."""
    service = wm_pb2.DESCRIPTOR.services_by_name["WorkingMemory"]
    factories = {
        (False, False): grpc.unary_unary_rpc_method_handler,
        (False, True): grpc.unary_stream_rpc_method_handler,
        (True, False): grpc.stream_unary_rpc_method_handler,
        (True, True): grpc.stream_stream_rpc_method_handler,
    }
    handlers = {}
    for method in service.methods:
        request_cls = getattr(wm_pb2, method.input_type.name)
        response_cls = getattr(wm_pb2, method.output_type.name)
        factory = factories[(method.client_streaming, method.server_streaming)]
        handlers[method.name] = factory(
            getattr(servicer, method.name),
            request_deserializer=request_cls.FromString,
            response_serializer=_serialize_watch if method.name == "Watch" else response_cls.SerializeToString,
        )
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(service.full_name, handlers),))
