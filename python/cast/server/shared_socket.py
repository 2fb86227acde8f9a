"""The server's shared-memory socket: the sessions of clients on its host.

The protocol is docs/client-protocol.md, "Large values by shared memory". A
Unix stream socket in the abstract namespace (``@cast-<server id>``): it
has no file, so nothing is left behind when the server dies, and it is
reachable only from the server's network namespace, which is what "on the
server's host" means here (a client in another namespace or on another
machine cannot connect, and gets bytes). A connection becomes a session once
its HELLO passes: the peer runs as the server's own OS user (``SO_PEERCRED``)
and its token is valid. The session's identity is the token's; its staging
area, and each arena segment before the first value lent from it, reach the
client as memory files (``SCM_RIGHTS``). A session's WRITES frames are its
Write-stream requests, applied on the loop as they are read
(:mod:`cast.server.socket_writes`). The rules are the core's
(:mod:`cast.core.shared`, :mod:`cast.core.access`); this module only moves frames.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import struct
from collections import deque
from collections.abc import Callable

from cast.core.access import Access
from cast.core.arena import Segment
from cast.core.shared import Lent, SharedSession
from cast.core.system import System
from cast.errors import CastError, InvalidArgumentError
from cast.server.rpc import Authenticator, Context
from cast.server.socket_writes import MAX_UNSENT, SocketWrites
from cast.v1 import directory_pb2
from cast.wire import shared_memory as wire

__all__ = ["METADATA_KEY", "SharedSocket", "read_session"]

log = logging.getLogger("cast.server")

METADATA_KEY = "cast-shared-memory"
"""Call metadata naming the caller's session and call: ``<session id hex>/<call number>``."""

_HELLO_S = 5.0  # how long a connection may take to say HELLO
_RETIRE_EVERY_S = 1.0  # how often empty segments are looked for
_FAREWELL_S = 2.0  # how long a refused connection's last frames (REFUSED the last) wait for the client to read them
_UCRED = struct.Struct("3i")  # pid, uid, gid


def read_session(access: Access, context: Context) -> tuple[SharedSession, int] | None:
    """The session and call a read names in its metadata, or None (it gets bytes).

    A malformed value is INVALID_ARGUMENT; another component's session is
    PERMISSION_DENIED (:meth:`cast.core.shared.SharedMemory.session_for`).
    """
    shared = access.system.shared
    if shared is None:
        return None
    for key, value in context.invocation_metadata() or ():
        if key == METADATA_KEY:
            text = value.decode() if isinstance(value, bytes) else value
            session_hex, sep, call = text.partition("/")
            try:
                session_id = bytes.fromhex(session_hex)
                number = int(call)
            except ValueError:
                number = -1
            if not sep or number < 0 or len(session_id) != 16:
                raise InvalidArgumentError(
                    f"{METADATA_KEY} metadata {text!r} is not SESSION/CALL (the session id in hex from WELCOME, "
                    "a call number): docs/client-protocol.md, \"Large values by shared memory\""
                )
            session = shared.session_for(access.who, session_id)
            return None if session is None else (session, number)
    return None


class _Connection:
    """One client's connection: frames in and out, and its session once HELLO passed."""

    def __init__(self, owner: SharedSocket, sock: socket.socket) -> None:
        self._owner = owner
        self._sock = sock
        self._loop = owner.loop
        self._reader = wire.FrameReader()
        self._pending: deque[tuple[bytes, int | None]] = deque()  # frames waiting for room in the socket
        self.session: SharedSession | None = None
        self.closed = False
        self._unsent = 0  # bytes of the frames in _pending
        self._reading = True  # the loop reads the socket (not paused)
        self._busy = False  # paused by the writes: frames read wait to be applied
        self._writes: SocketWrites | None = None  # the session's WRITES, once HELLO passed
        self._listeners: list[Callable[[], None]] = []  # told when it closes or its unsent frames went out
        self._loop.add_reader(sock.fileno(), self._readable)
        self._hello_timer = self._loop.call_later(_HELLO_S, self._too_slow)

    # --------------------------------------------------------------- reading

    def _readable(self) -> None:
        try:
            data, fds = self._owner.inbox.receive(self._sock)
        except (BlockingIOError, InterruptedError):
            return
        except (OSError, wire.ProtocolError) as exc:
            self.close(f"read failed: {exc}")
            return
        if not data:
            _close_all(fds)
            self.close("")
            return
        try:
            frames = self._reader.feed(data, fds)
        except wire.ProtocolError as exc:
            self.refuse(f"bad frame: {exc}")
            return
        finally:
            # Clients send no memory files: any that came is closed at once, whatever becomes of the read.
            _close_all(self._reader.stray())
        _close_all([frame.fd for frame in frames if frame.fd is not None])
        for frame in frames:
            if self.closed:
                return
            try:
                self._handle(frame)
            except (wire.ProtocolError, CastError) as exc:
                if self._writes is not None:
                    self._writes.apply()  # the WRITES before the bad frame: applied, as when each came alone
                self.refuse(str(exc) if isinstance(exc, wire.ProtocolError) else exc.message)
                return
        if self._writes is not None and not self.closed:  # one REPLIES frame for the WRITES of this read
            self._writes.apply()

    def _handle(self, frame: wire.Frame) -> None:
        shared = self._owner.system.shared
        assert shared is not None
        if self.session is None:
            if frame.kind != wire.HELLO:
                raise wire.ProtocolError(f"the first frame must be HELLO ({wire.HELLO}), not kind {frame.kind}")
            self._hello(frame.body)
            return
        if frame.kind == wire.RELEASE:
            shared.give_back(self.session, wire.parse_release(frame.body))
        elif frame.kind == wire.RECEIVED:
            call, count, ended = wire.parse_received(frame.body)
            shared.received(self.session, call, count, ended)
        elif frame.kind == wire.WRITES:
            assert self._writes is not None
            self._writes.received(frame.body)
        elif frame.kind == wire.NUDGE:
            # A thread of the client blocked in the socket's read, to be woken (docs/client-protocol.md, "Frames").
            if frame.body:
                raise wire.ProtocolError(f"NUDGE carries nothing, this one {len(frame.body)} bytes")
            if not self._pending:  # else the client has bytes to read already: its reader is not blocked
                self.send(wire.NUDGED_FRAME)
        else:
            raise wire.ProtocolError(f"unknown frame kind {frame.kind} from a client")

    def _hello(self, body: bytes) -> None:
        self._hello_timer.cancel()
        version, token = wire.parse_hello(body)
        if not 1 <= version <= wire.VERSION:
            raise wire.ProtocolError(
                f"protocol version {version} is not served (this server speaks 1 to {wire.VERSION})"
            )
        pid, uid, _ = _UCRED.unpack(self._sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size))
        if uid != os.geteuid():
            raise wire.ProtocolError(
                f"process {pid} runs as OS user {uid} and this server as {os.geteuid()}: shared memory is "
                "offered to the server's own OS user only; values travel as bytes"
            )
        who = self._owner.auth.verify(token)  # UNAUTHENTICATED, as a CastError: refused with its message
        auth = self._owner.auth
        shared = self._owner.system.shared
        assert shared is not None
        session = shared.open_session(who)
        session.send_segment = self._send_segment
        session.link = self
        self.session = session
        self._writes = SocketWrites(self._owner.system, lambda: auth.verify_until(token), self.send,
                                    self._pause_writes, session)
        frame = wire.welcome(session.id, bytes.fromhex(shared.server_id), shared.settings.threshold_bytes,
                             shared.settings.window_bytes, session.staging_bytes)
        if self.send(frame, session.staging_fd) and not self._pending:
            session.forget_staging_fd()  # the client has it; the server's mapping is all the server needs

    def _pause_writes(self, paused: bool) -> None:
        self._busy = paused
        self._read_or_not()

    def _read_or_not(self) -> None:
        """Read the socket unless its writes wait to be applied (or, held, fill their bound: SocketWrites)."""
        if self.closed:
            return
        want = not self._busy
        if want != self._reading:
            self._reading = want
            if want:
                self._loop.add_reader(self._sock.fileno(), self._readable)
            else:
                self._loop.remove_reader(self._sock.fileno())

    def _too_slow(self) -> None:
        if self.session is None:
            self.refuse(f"no HELLO within {_HELLO_S:g} s")

    # --------------------------------------------------------------- writing

    @property
    def unsent(self) -> int:
        """Bytes of frames waiting for room in the socket."""
        return self._unsent

    def listen(self, fn: Callable[[], None]) -> Callable[[], None]:
        """Call ``fn`` (on the loop) when the connection closes or its unsent frames went out."""
        self._listeners.append(fn)
        return lambda: self._listeners.remove(fn) if fn in self._listeners else None

    def _tell(self) -> None:
        for fn in list(self._listeners):
            fn()

    def _send_segment(self, segment: Segment) -> bool:
        return self.send(wire.segment(segment.id, segment.size), segment.fd)

    def send(self, frame: bytes, fd: int | None = None) -> bool:
        """Send a frame now, or as soon as the socket has room (in order); False once closed."""
        if self.closed:
            return False
        if not self._pending:
            try:
                sent = _send_frame(self._sock, frame, fd)
            except OSError as exc:
                self.close(f"write failed: {exc}")
                return False
            if sent == len(frame):
                return True
            frame, fd = frame[sent:], None if sent else fd
            self._loop.add_writer(self._sock.fileno(), self._writable)
        # A descriptor waiting here belongs to a live segment or the session's staging area: it stays open.
        self._pending.append((frame, fd))
        self._unsent += len(frame)
        self._hold_or_not()
        return True

    def _writable(self) -> None:
        try:
            self._unsent -= _send_some(self._sock, self._pending)
        except OSError as exc:
            self.close(f"write failed: {exc}")
            return
        if self._pending:
            self._hold_or_not()
            return
        self._loop.remove_writer(self._sock.fileno())
        self._hold_or_not()
        self._tell()

    def _hold_or_not(self) -> None:
        """Hold the client's writes while more than MAX_UNSENT bytes wait for it (its socket is still read)."""
        if self._writes is not None and not self.closed:
            self._writes.hold(self._unsent > MAX_UNSENT)

    def refuse(self, reason: str) -> None:
        """End the session now and tell the client why: REFUSED, after the frames still waiting to be sent."""
        if self.closed:
            return
        # REFUSED goes behind what waits: sent now, it could land inside a frame half sent (the client would
        # read a broken frame) or find the socket full (and be lost).
        last = self._pending
        self._pending = deque()
        last.append((wire.refused(reason), None))
        self.close(reason, last)

    def close(self, reason: str, last: deque[tuple[bytes, int | None]] | None = None) -> None:
        """End the connection and its session (everything it held is given back); ``last``: frames sent first."""
        if self.closed:
            return
        self.closed = True
        self._hello_timer.cancel()
        with contextlib.suppress(Exception):
            self._loop.remove_reader(self._sock.fileno())
            self._loop.remove_writer(self._sock.fileno())
        if last:
            _Farewell(self._owner, self._sock, last)  # before the session lets go of the descriptors
        else:
            self._sock.close()
        _close_all(self._reader.stray())
        self._pending.clear()
        self._unsent = 0
        if self._writes is not None:
            self._writes.close()
        shared = self._owner.system.shared
        if self.session is not None and shared is not None:
            shared.close_session(self.session)
        self._owner.connections.discard(self)
        self._tell()
        self._listeners.clear()
        if reason:
            log.info("shared-memory connection closed: %s", reason)


class _Farewell:
    """A closed connection's socket, sending its last frames before it closes, for ``_FAREWELL_S`` at most.

    Its session has already ended: nothing waits on these frames but the client. A descriptor that
    goes with one is a duplicate, so that a segment retired meanwhile cannot make its number name
    another file by the time it is sent; the duplicates are closed with the socket.
    """

    def __init__(self, owner: SharedSocket, sock: socket.socket, frames: deque[tuple[bytes, int | None]]) -> None:
        self._owner = owner
        self._sock = sock
        self._frames: deque[tuple[bytes, int | None]] = deque()
        self._fds: list[int] = []
        for frame, fd in frames:
            if fd is not None:
                try:
                    fd = os.dup(fd)
                except OSError:  # out of descriptors: that frame, not yet begun (one begun has none), is left out
                    continue
                self._fds.append(fd)
            self._frames.append((frame, fd))
        self._timer = owner.loop.call_later(_FAREWELL_S, self.close)
        self._writing = False
        owner.farewells.add(self)
        self._send()

    def _send(self) -> None:
        try:
            _send_some(self._sock, self._frames)
        except OSError:
            self.close()  # the client has gone: nothing to tell it
            return
        if not self._frames:
            self.close()
        elif not self._writing:
            self._writing = True
            self._owner.loop.add_writer(self._sock.fileno(), self._send)

    def close(self) -> None:
        """Close the socket, its frames sent or not, and the duplicated descriptors."""
        if self._sock.fileno() < 0:
            return
        self._timer.cancel()
        if self._writing:
            with contextlib.suppress(Exception):
                self._owner.loop.remove_writer(self._sock.fileno())
        self._sock.close()
        _close_all(self._fds)
        self._fds.clear()
        self._frames.clear()
        self._owner.farewells.discard(self)


class SharedSocket:
    """The listening socket of one server's shared memory, and its connections."""

    def __init__(self, system: System, auth: Authenticator) -> None:
        assert system.shared is not None
        self.system = system
        self.auth = auth
        self.name = f"cast-{system.shared.server_id}"
        self.connections: set[_Connection] = set()
        self.farewells: set[_Farewell] = set()  # refused connections sending their last frames
        self.inbox = wire.Inbox()  # every connection's reads: all on the loop, each fed to its reader at once
        self.loop = asyncio.get_running_loop()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_NONBLOCK | socket.SOCK_CLOEXEC)
        self._sock.bind("\0" + self.name)
        self._sock.listen(64)
        self.loop.add_reader(self._sock.fileno(), self._accept)
        self._retirer = asyncio.ensure_future(self._retire())

    def info(self) -> directory_pb2.SharedMemoryInfo:
        """What DescribeSystem tells clients of it."""
        shared = self.system.shared
        assert shared is not None
        return directory_pb2.SharedMemoryInfo(socket=self.name, server_id=shared.server_id, reads=True)

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.warning("shared-memory socket: accept failed: %s", exc)
                return
            sock.setblocking(False)
            self.connections.add(_Connection(self, sock))

    async def _retire(self) -> None:
        shared = self.system.shared
        assert shared is not None
        while True:
            await asyncio.sleep(_RETIRE_EVERY_S)
            for segment_id in shared.retire_empty():
                for connection in list(self.connections):
                    if connection.session is not None:
                        connection.send(wire.retire(segment_id))

    def close(self) -> None:
        """Stop listening and end every session."""
        self._retirer.cancel()
        with contextlib.suppress(Exception):
            self.loop.remove_reader(self._sock.fileno())
        self._sock.close()
        for connection in list(self.connections):
            connection.close("")
        for farewell in list(self.farewells):
            farewell.close()


def _send_frame(sock: socket.socket, frame: bytes, fd: int | None) -> int:
    """Send what of ``frame`` the socket takes now (0 if full), ``fd`` with its first byte; OSError once broken."""
    try:
        if fd is None:
            return sock.send(frame)
        return sock.sendmsg([frame], [(socket.SOL_SOCKET, socket.SCM_RIGHTS, struct.pack("i", fd))])
    except (BlockingIOError, InterruptedError):
        return 0


def _send_some(sock: socket.socket, frames: deque[tuple[bytes, int | None]]) -> int:
    """Send ``frames`` in order, taking off those sent, until the socket is full; the bytes sent. OSError once broken.

    A frame begun stays first with what is left of it, without its descriptor (it went with the first byte).
    """
    total = 0
    while frames:
        frame, fd = frames[0]
        sent = _send_frame(sock, frame, fd)
        total += sent
        if sent < len(frame):
            if sent:
                frames[0] = (frame[sent:], None)
            return total
        frames.popleft()
    return total


def _close_all(fds: list[int]) -> None:
    """Close descriptors a client sent (the server uses none of them)."""
    for fd in fds:
        with contextlib.suppress(OSError):
            os.close(fd)


def lend(access: Access, read: tuple[SharedSession, int] | None, record_shared: object) -> Lent | None:
    """Lend a record's value to the reader's session, when it has one and the value is in shared memory."""
    if read is None or record_shared is None:
        return None
    return access.lend(read[0], read[1], record_shared)
