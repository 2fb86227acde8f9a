"""One link to one server: its channel with the client's options, its stubs, errors and reconnect backoff.

Shared by the gRPC transport, the watch stream and the session, so that every
stream and call to a server goes through the same channel and the same error
mapping.
"""

from __future__ import annotations

import gc
import random
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import grpc

from cast.client.credentials import ClientTls
from cast.errors import ERROR_TRAILER, CastError, UnavailableError, error_for_code
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import inspection_pb2_grpc as insp_grpc
from cast.v1 import task_manager_pb2_grpc as tm_grpc
from cast.v1 import working_memory_pb2_grpc as wm_grpc

if TYPE_CHECKING:
    from cast.client.shm import SharedLink
    from cast.client.watch_stream import WatchStream
    from cast.client.write_stream import WriteStream

__all__ = ["CHANNEL_OPTIONS", "JOIN_S", "TRANSIENT", "Backoff", "LinkClosedError", "ServerLink", "map_rpc_error"]

JOIN_S = 2.0
"""How long closing a link waits for the threads of its streams to end (they end at once when all is well)."""

MAX_MESSAGE_BYTES = 64 * 1024 * 1024
CHANNEL_OPTIONS = (
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.keepalive_time_ms", 10_000),
    ("grpc.keepalive_timeout_ms", 5_000),
    # Since gRPC 1.5x a ping's own timeout (one minute by default) decides when an unanswered keepalive
    # ends the connection, not keepalive_timeout_ms: without it a hung server is noticed after a minute.
    ("grpc.http2.ping_timeout_ms", 5_000),
    ("grpc.keepalive_permit_without_calls", 1),
    # Try again soon after the server went away (gRPC's default backoff grows to two minutes),
    # so a restarted server is found within a few seconds.
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 2_000),
)

# Errors after which a stream is opened again (the server went away, or the connection broke);
# any other error ends the stream for good and is reported.
TRANSIENT = ("UNAVAILABLE", "UNKNOWN", "INTERNAL", "CANCELLED", "DEADLINE_EXCEEDED", "UNAUTHENTICATED")


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
    trailer = ""
    metadata: Any = exc.trailing_metadata() if hasattr(exc, "trailing_metadata") else None
    for key, value in metadata or ():
        if key == ERROR_TRAILER:
            trailer = value if isinstance(value, str) else value.decode()
    return error_for_code(name, details or name, trailer)


class LinkClosedError(UnavailableError):
    """A call made on a link after it was closed (the client closed), in place of gRPC's ``ValueError``.

    gRPC raises ``ValueError("Cannot invoke RPC on closed channel!")`` for a
    call on a closed channel: a stream thread that checked the client was open
    and then opened its call as the client closed meets it, and so does a
    read made after ``close()``. The stream threads end quietly on this
    error; a caller gets it as the CastError it is.
    """


class ServerLink:
    """One server endpoint: its channel and stubs."""

    def __init__(self, endpoint: str, tls: ClientTls | None = None) -> None:
        self.endpoint = endpoint
        self.closed = False  # close() began: no call may start on the channel any more
        if tls is None:
            self.channel = grpc.insecure_channel(endpoint, options=CHANNEL_OPTIONS)
        else:
            options = [*CHANNEL_OPTIONS, *tls.channel_options()]
            self.channel = grpc.secure_channel(endpoint, tls.credentials(), options=options)
        self.wm = wm_grpc.WorkingMemoryStub(self.channel)
        self.tm = tm_grpc.TaskManagerStub(self.channel)
        self.directory = dir_grpc.DirectoryStub(self.channel)
        self.inspection = insp_grpc.InspectionStub(self.channel)  # Report: a component's outcomes
        self.watch_stream: WatchStream | None = None
        self.write_stream: WriteStream | None = None  # opened by the first write (cast.client.write_stream)
        self.shared: SharedLink | None = None  # shared memory with this server, if on its host (cast.client.shm)
        self.session_id = ""
        self.registered = threading.Event()  # a session is open on this server
        # Heartbeat streams wait on a count, not an Event: a waiter clearing an Event could swallow the
        # wake-up of close() meant for another stream's generator (an old one, still being read by gRPC).
        self._beats = threading.Condition()
        self._beat_count = 0
        self._threads: list[threading.Thread] = []  # what close() joins: see track()
        self._request_readers: weakref.WeakSet[Iterator[Any]] = weakref.WeakSet()  # open_stream's wrapped requests
        self._threads_lock = threading.Lock()

    def beat_now(self) -> None:
        """Have every heartbeat stream of this link send at once (the state changed, or the client is closing)."""
        with self._beats:
            self._beat_count += 1
            self._beats.notify_all()

    def beats_asked(self) -> int:
        """How many times :meth:`beat_now` was called so far (what :meth:`wait_beat` compares with)."""
        return self._beat_count

    def wait_beat(self, seen: int, every: float) -> int:
        """Wait until :meth:`beat_now` was called since ``seen``, or ``every`` seconds; the count now."""
        with self._beats:
            self._beats.wait_for(lambda: self._beat_count != seen, every)
            return self._beat_count

    def track(self, thread: threading.Thread) -> None:
        """Have :meth:`close` wait for ``thread``, one that reads or writes a stream of this link.

        A thread still inside a gRPC call when the interpreter shuts down can die holding the
        call's lock; the call's finaliser then waits for that lock for ever and the process never
        exits. So no stream thread may outlive close().
        """
        with self._threads_lock:
            self._threads = [t for t in self._threads if t.is_alive()]
            self._threads.append(thread)

    def open_stream(self, method: Callable[..., Any], request: Any, **kwargs: Any) -> Any:
        """``method(request, **kwargs)``: a streaming call whose request reader gRPC starts is tracked too.

        Python's gRPC gives no handle on the thread that reads a request iterator, so the iterator is
        wrapped to name it: its first ``next`` runs on that thread. Until then (a loaded machine may
        not have run it yet when the client closes) :meth:`close` finds it by what it references.
        """
        if hasattr(request, "__next__"):
            request = self._read_by_tracked_thread(request)
            self._request_readers.add(request)
        return self.invoke(method, request, **kwargs)

    def invoke(self, method: Callable[..., Any], request: Any, **kwargs: Any) -> Any:
        """``method(request, **kwargs)`` (a stub's method of this link); LinkClosedError once the link closed."""
        try:
            return method(request, **kwargs)
        except ValueError:
            if not self.closed:
                raise
        raise LinkClosedError(f"the client's connection to {self.endpoint} is closed: no more calls on it")

    def _read_by_tracked_thread(self, requests: Iterator[Any]) -> Iterator[Any]:
        self.track(threading.current_thread())
        yield from requests

    def _pollers(self) -> list[threading.Thread]:
        """The channel's poller: the thread gRPC runs while the channel has streams.

        Closing the channel returns once every call has ended, but the poller may still be running the
        last call's end handler, inside that call's lock. Python's gRPC names it nowhere: the thread is
        found through what it references (its target holds the ``channel_spin`` function whose closure
        holds the channel's call state), never through its running frame, whose ``f_locals`` another
        thread must not read (CPython 3.11 crashed there). If gRPC changes these private names,
        nothing is found and nothing breaks.
        """
        state = getattr(self.channel, "_call_state", None)
        if state is None:
            return []
        return [thread for thread in threading.enumerate() if _runs(thread, "channel_spin", {id(state)})]

    def _request_threads(self) -> list[threading.Thread]:
        """The threads gRPC started to read this link's request iterators, whether they began reading or not.

        Found as :meth:`_pollers` is: gRPC's ``consume_request_iterator`` closes over the iterator.
        """
        readers = {id(reader) for reader in list(self._request_readers)}
        if not readers:
            return []
        return [thread for thread in threading.enumerate() if _runs(thread, "consume_request_iterator", readers)]

    def close(self, deadline: float | None = None) -> None:
        """Close the channel (every stream on it ends), wait for its threads, then end its shared-memory session.

        ``deadline`` is a ``time.monotonic()`` instant; the default is :data:`JOIN_S` from now.
        """
        self.closed = True
        self.channel.close()
        end = time.monotonic() + JOIN_S if deadline is None else deadline
        me = threading.current_thread()
        with self._threads_lock:
            threads = [t for t in self._threads if t is not me]
        for thread in [*threads, *self._request_threads(), *self._pollers()]:
            thread.join(max(0.0, end - time.monotonic()))
        if self.shared is not None:
            self.shared.close()


def _runs(thread: threading.Thread, name: str, values: set[int]) -> bool:
    """Whether ``thread`` runs a gRPC function called ``name`` that closes over one of ``values`` (their ids).

    gRPC starts its threads' functions (``channel_spin``, ``consume_request_iterator``) through a
    Cython wrapper whose closure scope is no Python closure: the function is one or two references
    away from the thread's target (``gc.get_referents`` reads them without running anything).
    """
    target = getattr(thread, "_target", None)  # threading deletes it once the thread's run ends
    if target is None:
        return False
    near = [target, *gc.get_referents(target)]
    for holder in [*near, *(ref for obj in near if not isinstance(obj, dict) for ref in gc.get_referents(obj))]:
        if getattr(holder, "__name__", None) == name and _closes_over(holder, values):
            return True
    return False


def _closes_over(function: object, values: set[int]) -> bool:
    for cell in getattr(function, "__closure__", None) or ():
        try:
            if id(cell.cell_contents) in values:
                return True
        except ValueError:  # an empty cell
            continue
    return False


class Backoff:
    """Exponential backoff with jitter for reconnecting: 0.1 s doubling to 3 s by default."""

    def __init__(self, initial: float = 0.1, maximum: float = 3.0) -> None:
        self.initial = initial
        self.maximum = maximum
        self._next = initial

    def reset(self) -> None:
        """Back to the initial delay (after a successful connection)."""
        self._next = self.initial

    def next(self) -> float:
        """The delay before the next attempt (grows each time)."""
        delay = self._next * random.uniform(0.8, 1.2)
        self._next = min(self.maximum, self._next * 2)
        return delay
