"""The Watch stream of one component to one server: watches created, events delivered, resumed after a reconnect."""

from __future__ import annotations

import collections
import functools
import logging
import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any

import grpc

from cast.client.channel import TRANSIENT, Backoff, LinkClosedError, ServerLink, map_rpc_error
from cast.client.conversions import event_from_pb, filter_to_pb, native_turn, turn_events
from cast.client.credentials import TokenSource
from cast.client.dispatcher import HIGH, Dispatcher
from cast.client.shm_session import ReadCall, receive_module
from cast.client.transport import EventSink
from cast.core.watch import EventFilter
from cast.errors import CastError, DeadlineExceededError, HistoryExpiredError, UnavailableError, error_for_code
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["EVENTS_METADATA", "WatchStream"]

EVENTS_METADATA = ("cast-watch-events", "socket")
"""Call metadata asking the server for the call's event batches as EVENTS frames on the session's socket."""

log = logging.getLogger("cast.client")

_receive = receive_module()


class _Watch:
    """What the client keeps of one watch so that it can be created again after a reconnect."""

    __slots__ = ("base", "filters", "first_starts", "latest", "sas", "watch_id")

    def __init__(
        self, watch_id: int, filters: Sequence[EventFilter], starts: dict[str, int], latest: bool = False
    ) -> None:
        self.watch_id = watch_id
        self.latest = latest
        self.filters = list(filters)
        self.first_starts = starts
        self.sas: list[str] = []  # the SAs of this server the watch covers (known once created)
        # Per SA, the revision the watch is known to have seen up to (None until created).
        self.base: dict[str, int] | None = None


class WatchStream:
    """One Watch call to one server, shared by every watch of the component on that server.

    When the connection breaks the stream is opened again with backoff and every
    watch is created again from the revision after the last one it got (per SA):
    no gap and no duplicate. The server's history id comes along, so a server that
    lost that history (restarted without persistence) refuses the resume, and the
    component is told to resynchronise (``watch_failed`` with HistoryExpiredError).
    """

    def __init__(
        self,
        server: ServerLink,
        tokens: TokenSource,
        sink: EventSink,
        on_error: Callable[[CastError], None],
        closing: threading.Event,
        dispatcher: Dispatcher | None = None,
    ) -> None:
        self._server = server
        # Reads the call's EVENTS frames on its own thread (docs/client-protocol.md, "A watch's events on the
        # session's socket"); None: the events come on the gRPC call.
        self._dispatcher = dispatcher
        # The EVENTS frames of the current call not yet turned into events, in the order read; _frames_lock
        # orders turning them (on the dispatcher) against the call's end (on this stream's thread).
        self._frames: collections.deque[bytes] = collections.deque()
        self._frames_lock = threading.RLock()
        self._turning = False  # the dispatcher is turning frames (a claim that reads the socket only queues more)
        self._socket_broke = ""  # why the session carrying the current call's events ended
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
        self._read: ReadCall | None = None  # the call's part of the shared-memory session (cast.client.shm)
        self._opened = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"cast-watch-{server.endpoint}", daemon=True)
        self._thread.start()
        server.track(self._thread)
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
            history_id=history_id, delivery=wm_pb2.DELIVERY_LATEST if w.latest else wm_pb2.DELIVERY_QUEUE,
        )
        return wm_pb2.WatchRequest(create=create)

    def _open(self) -> Any:
        with self._mutex:
            if self._closed:
                # close() ran since the stream's loop looked: a new call's request reader would wait for the
                # end of a queue nobody ends any more.
                raise LinkClosedError(f"the watch stream to {self._server.endpoint} is closed")
            if self._requests is not None:
                self._requests.put(None)  # the broken stream's request reader ends, instead of waiting for ever
            requests: queue.SimpleQueue[wm_pb2.WatchRequest | None] = queue.SimpleQueue()
            self._requests = requests
            for w in self._watches.values():
                requests.put(self._create_request(w))
            shared = self._server.shared
            session = shared.session() if shared is not None else None
            self._read = read = session.new_call() if session is not None else None
            metadata = self._tokens.metadata() + (read.metadata if read is not None else ())
            self._socket_broke = ""
            if read is not None and session is not None and self._dispatcher is not None:
                metadata += (EVENTS_METADATA,)
                session.event_handlers[read.number] = self._handler(read)
                session.on_end.append(functools.partial(self._session_ended, read))
                self._dispatcher.attach(session)
            self._call = self._server.open_stream(self._server.wm.Watch, iter(requests.get, None), metadata=metadata)
            return self._call

    # -------------------------------------------------------------- reader

    def _run(self) -> None:
        backoff = Backoff()
        first = True
        while not self._closed:
            try:
                call = self._open()
            except LinkClosedError:  # the transport closed since the check above
                self._opened.set()
                return
            if first:
                self._opened.set()
                first = False
            upgrade = False
            try:
                for resp in call:
                    if not self.connected:
                        self.connected = True
                        backoff.reset()
                        upgrade = self._read is None and self._sharing_now()
                    self._handle(resp)
                    if upgrade:
                        call.cancel()  # opened again at once, with the session: it resumes where this one is
                error: CastError = UnavailableError(f"the watch stream to {self._server.endpoint} ended")
            except grpc.RpcError as exc:
                error = map_rpc_error(exc)
            except CastError as exc:  # an event that could not be read (its shared memory): read the stream again
                call.cancel()
                error = UnavailableError(f"an event could not be read: {exc.message}")
            if self._socket_broke:  # the call was cancelled for it: resumed like a broken stream
                error = UnavailableError(f"the socket carrying the watch's events ended: {self._socket_broke}")
            self.connected = False
            self._end_shared()
            if self._closed or self._closing.is_set():
                return
            if upgrade:
                continue
            if error.code not in TRANSIENT:
                self._fail(error)
                return
            log.warning("watch stream to %s broke (%s); reconnecting", self._server.endpoint, error.message)
            self.reconnects += 1
            if self._closing.wait(backoff.next()):
                return

    def _sharing_now(self) -> bool:
        """Whether a shared-memory session with the server is open now, though it was not when this stream opened.

        A stream opened while its server was away (restarting) could not have
        one; once the server answers, the stream is opened again with it.
        """
        shared = self._server.shared
        return shared is not None and shared.session() is not None

    def _end_shared(self) -> None:
        """The call is over: say what it received (the server takes back the rest) and see if the session ended.

        EVENTS frames of the call not yet turned into events are dropped: the
        watches resume after the last event turned, so the next call sends
        them again (no gap, no duplicate), and their values were never
        claimed, so RECEIVED gives them back.
        """
        with self._frames_lock:
            read, self._read = self._read, None
            self._frames.clear()
            if read is not None:
                read.session.event_handlers.pop(read.number, None)
        if read is not None:
            read.end()
        if self._server.shared is not None:
            self._server.shared.check()

    def _handler(self, read: ReadCall) -> Callable[[bytes], None]:
        """What takes ``read``'s EVENTS frames: :meth:`_frame`, or (the compiled build) the same in C.

        The C handler turns a frame at once when it was read on the
        dispatcher thread and nothing of the call is queued or being turned,
        as :meth:`_frame` then :meth:`_turn_frames` would, and leaves every
        other case to :meth:`_frame`.
        """
        frame = functools.partial(self._frame, read)
        turn = native_turn()
        dispatcher = self._dispatcher
        if _receive is None or turn is None or dispatcher is None:
            return frame
        return _receive.DirectTurn(  # type: ignore[no-any-return]
            self, read, self._frames_lock, self._frames, read.claimer(), self._sink, self._seen, turn, turn_events,
            frame, dispatcher.ident,
        )

    def _frame(self, read: ReadCall, body: bytes) -> None:
        """An EVENTS frame of ``read``'s call, on the thread that read the session's socket (in the order read).

        On the dispatcher its events go to their callbacks at once; a frame
        another thread read (waiting for a segment, say) is queued for the
        dispatcher, behind those before it.
        """
        dispatcher = self._dispatcher
        assert dispatcher is not None
        with self._frames_lock:
            if read is not self._read or self._socket_broke:
                return  # the call ended or is ending: its watches resume after what was turned
            self._frames.append(body)
            if self._turning:
                return  # read by a claim of the frame being turned: turned next, in order
        if threading.get_ident() == dispatcher.ident:
            self._turn_frames()
        else:
            dispatcher.submit(self._turn_frames, block=False, priority=HIGH)

    def _turn_frames(self) -> None:
        """Turn the queued EVENTS frames into events, in order (on the dispatcher thread)."""
        with self._frames_lock:
            if self._turning:
                return
            self._turning = True
            try:
                read = self._read
                # Frames are queued only while their call's read is current; once broken, the rest comes again on
                # a new call.
                while read is not None and self._frames and not self._socket_broke:
                    turn_events(self._frames.popleft(), read, self._sink, self._seen)
            except CastError as exc:
                self._turn_failed(exc)
            finally:
                self._turning = False

    def _turn_failed(self, exc: CastError) -> None:
        """A value of the call's could not be claimed: the call is read again from here (under _frames_lock)."""
        self._socket_broke = exc.message
        call = self._call
        if call is not None:
            call.cancel()

    def _session_ended(self, read: ReadCall, why: str) -> None:
        """The session carrying ``read``'s events ended: the call ends too, and the watches resume on a new one."""
        with self._frames_lock:
            if read is not self._read:
                return
            self._socket_broke = why
            call = self._call
        if call is not None:
            call.cancel()

    def _events(self, resp: wm_pb2.WatchResponse, read: ReadCall | None) -> None:
        for pb in resp.events:
            event = event_from_pb(pb, read)
            self._sink(event, pb.watch_ids)
            if event.revision > self._seen.get(event.subarchitecture, 0):
                self._seen[event.subarchitecture] = event.revision

    def _handle(self, resp: wm_pb2.WatchResponse) -> None:
        if resp.events:
            self._events(resp, self._read)
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
        self,
        watch_id: int,
        filters: Sequence[EventFilter],
        starts: dict[str, int],
        timeout: float,
        latest: bool = False,
    ) -> dict[str, int]:
        """Create a watch and wait (up to ``timeout``) for the server to confirm it; every WM's revision.

        ``latest``: the server conflates what is pending for it to the newest change per entry.
        """
        done = threading.Event()
        box: list[Any] = []
        w = _Watch(watch_id, filters, starts, latest)
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
                    f"server {self._server.endpoint} unreachable: the watch was not created within {timeout:g} s"
                )
            with self._mutex:
                call = self._call
            if call is not None:
                call.cancel()  # the server looks hung: the stream is opened again, the other watches resume
            raise DeadlineExceededError(
                f"{self._server.endpoint} did not confirm watch {watch_id} within {timeout:g} s: the server looks "
                "hung, so the watch stream was ended; it opens again by itself and its other watches resume"
            )
        result = box[0]
        if isinstance(result, CastError):
            self._watches.pop(watch_id, None)
            raise result
        return dict(result)

    def cancel(self, watch_id: int) -> None:
        """Stop a watch (the server stops sending its events)."""
        with self._mutex:
            self._watches.pop(watch_id, None)
            if self._requests is not None:
                self._requests.put(wm_pb2.WatchRequest(cancel=wm_pb2.WatchCancel(watch_id=watch_id)))

    def close(self) -> None:
        """End the stream and its thread."""
        self._closed = True
        with self._mutex:
            if self._requests is not None:
                self._requests.put(None)
            call = self._call
        if call is not None:
            call.cancel()


