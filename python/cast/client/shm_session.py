"""One session with a server's shared memory, after its WELCOME (docs/client-protocol.md).

:class:`ClientSession`

- *stages* a large value: copies it into a free region of the staging area and
  names it in the write (``StagedValue``); the region is reused once the
  write's reply came (never while its outcome is unknown);
- *claims* a value the server lent (``SharedValue`` in an entry): a read-only
  view of the segment it is in (mapped once, when its SEGMENT frame came) and
  a :class:`Lease` that gives the value back (RELEASE) when the last object
  holding it is gone;
- counts the references each call received and says so when the call ends
  (RECEIVED), so that the server takes back what never arrived.

It also carries the component's Write-stream requests to that server
(:attr:`ClientSession.writes`, :mod:`cast.client.socket_writes`).

No thread of its own: frames from the server (SEGMENT, RETIRE, REFUSED,
EVENTS, REPLIES, the end) are read whenever the session is used, by the
thread that needs them. How a session is opened, and
when there is none: :mod:`cast.client.shm`.
"""

from __future__ import annotations

import collections
import functools
import importlib
import logging
import mmap
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from types import ModuleType

from cast.client.socket_writes import SessionWrites
from cast.core.arena import Extents, round_up
from cast.errors import CastError, UnavailableError
from cast.v1 import entry_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire import shared_memory as wire

__all__ = ["METADATA_KEY", "ClientSession", "Lease", "ReadCall", "Staged"]

log = logging.getLogger("cast.client")

METADATA_KEY = "cast-shared-memory"
"""The call metadata that names a read's session and call: ``<session id hex>/<call number>``."""

_SEGMENT_WAIT_S = 5.0  # how long a claim waits for the SEGMENT frame sent before the message naming it
_SEND_S = 5.0  # how long a frame may wait for room in the socket: the server reads it at once unless stuck
_READ_BYTES = 256 << 10  # one read takes what the socket holds (EVENTS frames carry small values' bytes)
_PAYLOAD_ALIGN = 64  # a loan's payload starts on a cache line (ClientSession.reserve)
_RECEIVED_EVERY = 64  # a long call reports what it received this often, so the server forgets the rest


def _c_module(name: str, switch: str) -> ModuleType | None:
    """``cast.client.<name>`` where the build has it (the compiled build), unless ``switch`` is 0 in the environment."""
    if os.environ.get(switch, "1") == "0":
        return None
    try:
        return importlib.import_module(f"cast.client.{name}")
    except ImportError:  # a pure build (make setup's editable install)
        return None


def native_module() -> ModuleType | None:
    """The C claims, leases and fields where the build has them (the compiled build), unless CAST_NATIVE_SHARED=0.

    Claiming a lent value, reading its field and giving it back cost a 30 Hz
    watcher a dozen Python functions per value in the pure path
    (docs/performance-m8.md, "Claims and leases in C");
    ``cast.client._shared_native`` does the same in C and leaves every case
    but the common one to the pure path.
    """
    return _c_module("_shared_native", "CAST_NATIVE_SHARED")


_native = native_module()
NATIVE_SHARED = _native is not None
"""Whether lent values are claimed, read and given back in C (the compiled build, unless CAST_NATIVE_SHARED=0)."""


@functools.cache  # configured once, whichever module asks first (this one, cast.client.watch_stream)
def receive_module() -> ModuleType | None:
    """The session's reads and frames in C where the build has it (the compiled build), unless CAST_NATIVE_RECEIVE=0.

    From the dispatcher's ``poll`` to a watch's decoder the pure path is a
    dozen Python functions per frame, 35-80 us of a 30 Hz watcher's
    latency on cold caches (docs/performance-m8.md, "The session's reads in
    C"); ``cast.client._receive_native`` does the same in C.
    """
    module = _c_module("_receive_native", "CAST_NATIVE_RECEIVE")
    if module is not None:
        module.configure(wire.Frame, wire.ProtocolError, CastError)
    return module


_receive = receive_module()
NATIVE_RECEIVE = _receive is not None
"""Whether session sockets are read and their frames cut in C (the compiled build, unless CAST_NATIVE_RECEIVE=0)."""


class Staged:
    """A region of the staging area holding one value, until its write's reply came."""

    __slots__ = ("offset", "size", "start", "taken")

    def __init__(self, offset: int, size: int, taken: int, start: int | None = None) -> None:
        self.offset = offset
        self.size = size  # the value's bytes
        self.taken = taken  # whole pages
        self.start = offset if start is None else start  # the region's first byte (a loan's value begins after it)


class Lease:
    """A value the server lent: given back (RELEASE) once this object is gone (records and views hold it)."""

    __slots__ = ("session", "value_id")

    def __init__(self, session: ClientSession, value_id: int) -> None:
        self.session = session
        self.value_id = value_id

    def __del__(self) -> None:
        # A finaliser of its own rather than weakref.finalize, which enters every lease in a global registry:
        # 0.8 us per event warm, more on the cold caches of a 30 Hz watcher. give_back never waits.
        self.session.give_back(self.value_id)


class ReadCall:
    """One read call (a Get, a watch stream): its metadata, and the references it received."""

    __slots__ = ("count", "ended", "metadata", "number", "session")

    def __init__(self, session: ClientSession, number: int) -> None:
        self.session = session
        self.number = number
        self.count = 0
        self.ended = False
        self.metadata = ((METADATA_KEY, f"{session.id.hex()}/{number}"),)

    def claim(self, ref: entry_pb2.SharedValue) -> tuple[memoryview, Lease]:
        """The bytes of a value lent on this call, and its lease."""
        return self.claim_at(ref.segment, ref.offset, ref.size, ref.value_id)

    def claimer(self) -> Callable[[int, int, int, int], tuple[memoryview, Lease]]:
        """What claims a reference given by its fields: :meth:`claim_at`, or the same in C where the build has it."""
        return self.claim_at if _native is None else _native.Claimer(self)

    def claim_at(self, segment: int, offset: int, size: int, value_id: int) -> tuple[memoryview, Lease]:
        """:meth:`claim` of a reference given by its fields (what the native EVENTS decoder reads)."""
        self.count += 1
        if self.count % _RECEIVED_EVERY == 0:
            self.session.send(wire.received(self.number, self.count, False))
        return self.session.claim_at(segment, offset, size, value_id)

    def end(self, answered: bool = False) -> None:
        """The call is over: the server takes back what it sent and this call never received.

        ``answered``: the whole answer was read, so nothing was sent that did
        not arrive; with no reference in it there is nothing to say.
        """
        if not self.ended:
            self.ended = True
            if self.count or not answered:
                self.session.send(wire.received(self.number, self.count, True))


class _Segment:
    __slots__ = ("map", "size", "view")

    def __init__(self, fd: int, size: int) -> None:
        try:
            self.map = mmap.mmap(fd, size, prot=mmap.PROT_READ)
        finally:
            os.close(fd)  # the mapping keeps the memory file
        self.size = size
        self.view = memoryview(self.map)

    def close(self) -> bool:
        try:
            self.view.release()
            self.map.close()
        except BufferError:  # a value of it is still held: later
            self.view = memoryview(self.map)
            return False
        return True


class ClientSession:
    """One session with a server's shared memory (after WELCOME)."""

    def __init__(self, sock: socket.socket, body: bytes, staging_fd: int, endpoint: str, token: str) -> None:
        _, self.id, server_id, self.threshold, self.window, staging_size = wire.parse_welcome(body)
        self.server_id = server_id.hex()
        self.endpoint = endpoint
        self.token = token  # its HELLO's: the identity of every write sent here
        self.reads = False  # the server answers gets in WRITES frames (SharedMemoryInfo.reads)
        self._sock = sock
        try:
            self._staging = mmap.mmap(staging_fd, staging_size)
        finally:
            os.close(staging_fd)
        self._staging_view = memoryview(self._staging)
        self._regions = Extents(staging_size)
        self._quarantined = 0  # staged bytes of writes whose outcome is unknown: never reused
        self._reader = wire.FrameReader()
        self._inbox: wire.Inbox | None = None  # read under _read_lock (the pure path's; made at its first read)
        # The C reads and frames (the compiled build): its buffer and descriptors are the reader's and inbox's.
        self._receiver = None if _receive is None else _receive.Receiver(sock, _READ_BYTES)
        self._segments: dict[int, _Segment] = {}
        self._retired: list[_Segment] = []
        self._read_lock = threading.Lock()
        self._state = threading.Lock()  # the staging regions and the segment table
        self._send_lock = threading.Lock()
        self._unsent: collections.deque[int] = collections.deque()  # value ids given back, not yet sent
        # Write requests held back while others are in flight (SessionWrites), each a WRITES frame's entry: sent
        # together, before anything else this session sends, by the next thread that sends or reads a reply.
        self.held_writes: collections.deque[bytes] = collections.deque()
        self._calls = 0
        # call number -> what takes that watch call's EVENTS frames (run by whichever thread reads the socket)
        self.event_handlers: dict[int, Callable[[bytes], None]] = {}
        self.on_end: list[Callable[[str], None]] = []  # told why, once the session ended
        self.dead = ""  # why the session ended ("" while it lives)
        self.writes = SessionWrites(self)  # the Write-stream requests sent here

    # ---------------------------------------------------------------- writes

    def stage(self, data: bytes | memoryview) -> Staged | None:
        """``data`` copied into a free region of the staging area; None when there is no room (send the bytes)."""
        self.poll()  # a session the server ended (it restarted) is noticed before a write names it
        if self.dead:
            return None
        size = len(data)
        taken = round_up(size)
        with self._state:
            offset = self._regions.take(taken)
        if offset is None:
            return None
        try:
            self._staging_view[offset: offset + size] = data
        except ValueError:  # the session ended meanwhile (its staging area is unmapped)
            return None
        return Staged(offset, size, taken)

    def reserve(self, header: bytes, size: int) -> tuple[Staged, memoryview] | None:
        """A region for a loan (cast.client.loan): ``header`` written, then ``size`` bytes left to the caller.

        The payload (what follows the header) starts on a multiple of 64, as
        the arena places a value's largest field: a caller filling it with
        vector stores finds it aligned. The view returned is the region's
        value (header, then payload); it keeps the staging area mapped while
        it lives, even past the session's end. None: the session ended, or there
        is no room (the loan's bytes are then private memory).
        """
        self.poll()
        if self.dead:
            return None
        pad = -len(header) % _PAYLOAD_ALIGN
        value = len(header) + size
        taken = round_up(pad + value)
        with self._state:
            start = self._regions.take(taken)
        if start is None:
            return None
        offset = start + pad
        try:
            region = self._staging_view[offset: offset + value]
        except ValueError:  # the session ended meanwhile (its staging area's view was released)
            return None
        region[:len(header)] = header
        return Staged(offset, value, taken, start), region

    def staged_value(self, staged: Staged) -> wm_pb2.StagedValue:
        """What a write request says of a staged value."""
        return wm_pb2.StagedValue(session=self.id, offset=staged.offset, size=staged.size)

    def unstage(self, staged: Staged, known: bool) -> None:
        """The write's reply came (``known``): its region is free again; else it stays taken for good.

        A write whose outcome is unknown (its stream broke, its deadline
        passed) may still be applied later, and the server would then copy
        whatever the region holds: so nothing is written there again.
        """
        with self._state:
            if known:
                self._regions.give(staged.start, staged.taken)
            else:
                self._quarantined += staged.taken

    # ----------------------------------------------------------------- reads

    def new_call(self) -> ReadCall:
        """A read call on this session (its metadata names it)."""
        with self._state:
            self._calls += 1
            return ReadCall(self, self._calls)

    def claim_at(self, segment_id: int, offset: int, size: int, value_id: int) -> tuple[memoryview, Lease]:
        """A read-only view of a lent value's bytes and its lease; UnavailableError if its segment never came."""
        lease = Lease(self, value_id) if _native is None else _native.Lease(self, value_id)  # given back whatever next
        segment = self._segments.get(segment_id)
        if segment is None:
            segment = self._await_segment(segment_id)
        end = offset + size
        if end > segment.size:
            raise UnavailableError(
                f"the server at {self.endpoint} named bytes {offset}..{end} of shared-memory segment "
                f"{segment_id}, which has {segment.size}: read again"
            )
        return segment.view[offset: end], lease

    def _await_segment(self, segment_id: int) -> _Segment:
        # Sent before the message naming it: it is in the socket already, or comes at once.
        end = time.monotonic() + _SEGMENT_WAIT_S
        while True:
            self.poll(wait=max(0.0, min(0.1, end - time.monotonic())))
            segment = self._segments.get(segment_id)
            if segment is not None:
                return segment
            if self.dead or time.monotonic() >= end:
                raise UnavailableError(
                    f"shared-memory segment {segment_id} of the server at {self.endpoint} did not arrive "
                    f"({self.dead or f'within {_SEGMENT_WAIT_S:g} s'}): read again"
                )

    def send_held(self) -> None:
        """Send the write requests held back, unless another thread is sending (it sends them when it is done)."""
        if self.held_writes and self._send_lock.acquire(blocking=False):
            try:
                self._flush()
            finally:
                self._sent()

    def give_back(self, value_id: int) -> None:
        """A lease is gone: RELEASE it.

        Called from finalizers, on any thread, maybe inside a send of this
        session: it never waits for the send lock. If another thread holds it,
        that thread sends this too when it lets the lock go (:meth:`_sent`).
        """
        self._unsent.append(value_id)
        if self._send_lock.acquire(blocking=False):
            try:
                self._flush()
            finally:
                self._sent()

    # -------------------------------------------------------------- frames

    def send(self, frame: bytes) -> None:
        """Send a frame (after the RELEASEs and write requests waiting); nothing once the session is over."""
        self._send_lock.acquire()
        try:
            self._flush()
            self._write(frame)
        finally:
            self._sent()

    def send_write(self, entry: bytes) -> None:
        """Send a write request (a WRITES frame's entry) in one frame with those held back before it."""
        self._send_lock.acquire()
        try:
            self._flush(entry)
        finally:
            self._sent()

    def _sent(self) -> None:
        """Let the send lock go; then send what was given back meanwhile by a thread that could not take it."""
        self._send_lock.release()
        self._send_waiting()

    def _send_waiting(self) -> None:
        """Send what threads that could not take the send lock gave back or held meanwhile; call without the lock."""
        while (self._unsent or self.held_writes) and self._send_lock.acquire(blocking=False):
            try:
                self._flush()
            finally:
                self._send_lock.release()

    def _flush(self, entry: bytes = b"") -> None:
        """Send the RELEASEs waiting, then the write requests held back and ``entry`` after them, in one frame."""
        ids = []
        while self._unsent:
            ids.append(self._unsent.popleft())
        for start in range(0, len(ids), 8000):
            self._write(wire.release(ids[start: start + 8000]))
        held = self.held_writes
        if held:
            entries = []
            while held:
                entries.append(held.popleft())
            entries.append(entry)
            self._write(wire.writes(b"".join(entries)))
        elif entry:
            self._write(wire.writes(entry))

    def _write(self, frame: bytes) -> None:
        if self.dead:
            return
        view = memoryview(frame)
        end = time.monotonic() + _SEND_S
        while view:
            try:
                sent = self._sock.send(view)
            except (BlockingIOError, InterruptedError):
                if time.monotonic() > end:
                    self._end(f"the server has not read its socket for {_SEND_S:g} s")
                    return
                select.select([], [self._sock], [], 0.1)
                continue
            except OSError as exc:
                self._end(f"write failed: {exc}")
                return
            view = view[sent:]

    def fileno(self) -> int:
        """The session socket's descriptor (-1 once ended), for a thread that waits for frames."""
        return -1 if self.dead else self._sock.fileno()

    def reader(self) -> Callable[[], bool]:
        """:meth:`poll` without a wait, as one callable: the same in C where the build has it (the dispatcher's)."""
        receiver = self._receiver
        return self.poll if receiver is None else functools.partial(receiver.pump, self)

    def poll(self, wait: float = 0.0) -> bool:
        """Read what the server sent (SEGMENT, RETIRE, REFUSED, EVENTS, REPLIES, the end); wait ``wait`` s for it.

        False when another thread was reading (it handles what came).
        """
        if self.dead:
            return True
        if not (self._read_lock.acquire(timeout=wait) if wait else self._read_lock.acquire(blocking=False)):
            return False
        try:
            if wait:
                select.select([self._sock], [], [], wait)
            self._read_available()
        finally:
            self._stop_reading()
        return True

    @property
    def reading(self) -> bool:
        """Whether a thread is reading the socket now (it handles what comes, then says it left)."""
        return self._read_lock.locked()

    def read_until(self, done: Callable[[], bool], wait: float) -> bool:
        """Read and handle what comes until ``done()`` or ``wait`` s passed; False at once if another thread reads.

        A thread waiting for something the socket brings (a write's reply)
        reads it itself, rather than wait for a reader thread to hand it over.
        """
        if self.dead:
            return True
        if not self._read_lock.acquire(blocking=False):
            return False
        try:
            end = time.monotonic() + wait
            while not self.dead and not done():
                left = end - time.monotonic()
                if left <= 0 or not select.select([self._sock], [], [], left)[0]:
                    break
                self._read_available()
                if self.writes.answered:
                    break  # async writes answered: their callbacks run once it let go (SessionWrites)
        finally:
            self._stop_reading()
        return True

    def _stop_reading(self) -> None:
        """Let the read lock go: a writer waiting for a reader reads next; unmap what the frames retired.

        Last, the async writes answered meanwhile are settled, on this thread but no longer the reader.
        """
        self._read_lock.release()
        self._after_reading()

    def _after_reading(self) -> None:
        """What is left to do once the read lock was let go (the C reader calls it only when there is some)."""
        # Each looked at here before it is called: at every frame there is mostly nothing to do, and a call is what
        # a 30 Hz watcher's cold caches make dear (docs/performance-m8.md, "Claims and leases in C").
        writes = self.writes
        if writes.followers:
            writes.reader_left()
        if self._retired:
            self._close_retired()
        if writes.answered:
            writes.settle_answered()

    def _read_available(self) -> None:
        """Read and handle every frame the socket holds now. Call with the read lock held."""
        if self._receiver is not None:
            self._receiver.read_available(self)  # the same, in C
            return
        inbox = self._inbox
        if inbox is None:
            inbox = self._inbox = wire.Inbox(_READ_BYTES)
        while not self.dead:
            try:
                data, fds = inbox.receive(self._sock)
            except (BlockingIOError, InterruptedError):
                break
            except (OSError, wire.ProtocolError) as exc:
                self._end(f"read failed: {exc}")
                break
            if not data:
                self._end("the server closed the session")
                break
            drained = len(data) < inbox.size  # the socket held no more: no second read to learn it
            try:
                for frame in self._reader.feed(data, fds):
                    self._handle(frame)
            except wire.ProtocolError as exc:
                self._end(str(exc))
                break
            if drained:
                break

    def _handle(self, frame: wire.Frame) -> None:
        if frame.kind == wire.SEGMENT:
            segment_id, size = wire.parse_segment(frame.body)
            assert frame.fd is not None
            with self._state:
                self._segments[segment_id] = _Segment(frame.fd, size)
        elif frame.kind == wire.RETIRE:
            with self._state:
                gone = self._segments.pop(wire.parse_retire(frame.body), None)
                if gone is not None:
                    self._retired.append(gone)
        elif frame.kind == wire.EVENTS:
            call = int.from_bytes(frame.body[:8], "little")
            handler = self.event_handlers.get(call)
            if handler is not None:
                handler(frame.body[8:])
        elif frame.kind == wire.REPLIES:
            self.writes.replies(frame.body)
        elif frame.kind == wire.REFUSED:
            self._end(f"the server ended it: {frame.body.decode(errors='replace')}")
        elif frame.fd is not None:
            os.close(frame.fd)

    def _close_retired(self) -> None:
        with self._state:
            self._retired = [s for s in self._retired if not s.close()]

    def _end(self, why: str) -> None:
        if self.dead:
            return
        self.dead = why or "closed"
        log.debug("shared-memory session with %s ended: %s", self.endpoint, self.dead)
        self.writes.end(self.dead)
        for tell in self.on_end:
            tell(self.dead)
        self.on_end.clear()
        try:
            self._sock.close()
        except OSError:
            pass
        for fd in self._reader.stray() if self._receiver is None else self._receiver.stray():
            os.close(fd)
        with self._state:
            # Mappings still held by values go when those do (their leases keep this object).
            self._retired.extend(self._segments.values())
            self._segments.clear()
            self._retired = [s for s in self._retired if not s.close()]
            try:
                self._staging_view.release()
                self._staging.close()
            except BufferError:
                pass

    def close(self) -> None:
        """End the session (what it holds lent is given back by the server)."""
        self._end("closed")

    def abandon(self, why: str) -> None:
        """End the session because the server looks hung (``why``): what is outstanding on it fails."""
        self._end(why)

    def __del__(self) -> None:
        if not self.dead:
            try:
                self._sock.close()
            except Exception:  # noqa: BLE001 - an interpreter shutting down
                pass
