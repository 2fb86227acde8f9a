"""The frames of a shared-memory session on the server's Unix socket.

The protocol is docs/client-protocol.md, "Large values by shared memory".

A session is one Unix stream connection to the socket a server names in
``SystemDescription.shared_memory``. Every frame is a little-endian ``u32``
length (of what follows, at least 1) and then that many bytes: a ``u8`` kind
and its fields. A frame that carries a memory file is sent in one
``sendmsg`` with the descriptor as ``SCM_RIGHTS``; the descriptor arrives
no later than the frame's first byte, so a receiver keeps the descriptors it
gets in order and gives the next one to each frame that carries one.

Shared by the client library and the server (:mod:`cast.server.shared_socket`):
protobuf-free, gRPC-free.
"""

from __future__ import annotations

import array
import os
import socket
import struct
from collections import deque

__all__ = [
    "HELLO", "HELLO_VERSION", "MAX_FRAME", "MAX_WRITES_FRAME", "NUDGE", "NUDGED", "NUDGED_FRAME", "NUDGE_FRAME",
    "NUDGE_VERSION", "RECEIVED", "REFUSED", "RELEASE", "REPLIES", "RETIRE", "SEGMENT", "VERSION", "WELCOME", "WRITES",
    "Frame", "FrameReader", "Inbox", "ProtocolError", "encode", "hello", "receive", "received", "refused", "release",
    "replies", "retire", "segment", "send", "welcome", "writes",
]

VERSION = 2
"""The newest version of the protocol this module speaks: a server's, sent in WELCOME.

A server serves every version from 1 to its own; a client says in HELLO the
version it needs and uses what a later version adds only when WELCOME's
version has it (2: NUDGE).
"""

HELLO_VERSION = 1
"""The version this module's client says in HELLO: it uses nothing a later version adds."""

NUDGE_VERSION = 2
"""The first version whose servers answer NUDGE."""

# Client -> server
HELLO = 1  # u16 version, then the token (UTF-8) to the end
RELEASE = 2  # n x u64 value ids given back
RECEIVED = 3  # u64 call, u64 count, u8 ended
WRITES = 4  # a serialized cast.v1.WriteRequests (up to MAX_WRITES_FRAME)
NUDGE = 5  # nothing; answered by NUDGED (version 2)
# Server -> client
WELCOME = 10  # u16 version, 16 bytes session, 16 bytes server id, u64 threshold, u64 window, u64 staging size; 1 fd
REFUSED = 11  # the reason (UTF-8) to the end; the server then closes
SEGMENT = 12  # u32 segment id, u64 size; 1 fd
RETIRE = 13  # u32 segment id
REPLIES = 14  # a serialized cast.v1.WriteReplies (up to MAX_WRITES_FRAME)
EVENTS = 15  # u64 call, then a serialized cast.v1.WatchResponse (up to MAX_WRITES_FRAME)
NUDGED = 16  # nothing: the answer to a NUDGE (version 2)

MAX_FRAME = 1 << 16
"""The largest frame either side sends or accepts (a RELEASE of 8,000 ids fits), but WRITES and REPLIES."""

MAX_WRITES_FRAME = 64 << 20
"""The largest WRITES or REPLIES frame: a gRPC message's limit, so any request the Write stream takes fits one."""

LARGE = frozenset({4, 14, 15})  # WRITES, REPLIES: the kinds allowed up to MAX_WRITES_FRAME

WITH_FD = frozenset({WELCOME, SEGMENT})

_LEN = struct.Struct("<I")
_WELCOME = struct.Struct("<H16s16sQQQ")
_SEGMENT = struct.Struct("<IQ")
_RECEIVED = struct.Struct("<QQB")
_U32 = struct.Struct("<I")
_U16 = struct.Struct("<H")
_U64 = struct.Struct("<Q")


class ProtocolError(Exception):
    """A frame that breaks the protocol: the connection is closed."""


class Frame:
    """One decoded frame: its kind, its fields (after the kind byte), and the memory file it carries, if any."""

    # A class, not a NamedTuple: compiled (the compiled build), it is made in C, where a NamedTuple's __new__ is
    # Python code run for every frame on both sides (docs/performance-m8.md, "Claims and leases in C").
    __slots__ = ("body", "fd", "kind")

    def __init__(self, kind: int, body: bytes, fd: int | None) -> None:
        self.kind = kind
        self.body = body
        self.fd = fd

    def __repr__(self) -> str:
        return f"Frame(kind={self.kind}, body={self.body!r}, fd={self.fd})"


def encode(kind: int, body: bytes = b"") -> bytes:
    """A frame: length, kind, fields."""
    return _LEN.pack(len(body) + 1) + bytes((kind,)) + body


def hello(token: str) -> bytes:
    """HELLO: the protocol version and the caller's token."""
    return encode(HELLO, _U16.pack(HELLO_VERSION) + token.encode())


def release(value_ids: list[int]) -> bytes:
    """RELEASE: values given back (one lease each)."""
    return encode(RELEASE, struct.pack(f"<{len(value_ids)}Q", *value_ids))


def received(call: int, count: int, ended: bool) -> bytes:
    """RECEIVED: ``count`` references received on ``call`` so far; ``ended``: the call is over."""
    return encode(RECEIVED, _RECEIVED.pack(call, count, ended))


def writes(requests: bytes) -> bytes:
    """WRITES: a serialized ``cast.v1.WriteRequests``, applied as the Write stream applies it."""
    return encode(WRITES, requests)


def replies(body: bytes) -> bytes:
    """REPLIES: a serialized ``cast.v1.WriteReplies``, the answers to WRITES by request id."""
    return encode(REPLIES, body)


def events(call: int, response: bytes) -> bytes:
    """EVENTS: a watch call's event batch (an encoded ``cast.v1.WatchResponse``) on the session's socket."""
    return _LEN.pack(len(response) + 9) + bytes((EVENTS,)) + _U64.pack(call) + response


def welcome(session: bytes, server_id: bytes, threshold: int, window: int, staging: int) -> bytes:
    """WELCOME (sent with the staging area's memory file)."""
    return encode(WELCOME, _WELCOME.pack(VERSION, session, server_id, threshold, window, staging))


def refused(reason: str) -> bytes:
    """REFUSED: why the session is refused or ended."""
    return encode(REFUSED, reason.encode())


def segment(segment_id: int, size: int) -> bytes:
    """SEGMENT (sent with the segment's memory file)."""
    return encode(SEGMENT, _SEGMENT.pack(segment_id, size))


NUDGE_FRAME = encode(NUDGE)
"""NUDGE: the server answers NUDGED, which wakes a thread of the client blocked in the socket's read."""

NUDGED_FRAME = encode(NUDGED)
"""NUDGED: the server's answer to a NUDGE (nothing else)."""


def retire(segment_id: int) -> bytes:
    """RETIRE: unmap the segment once nothing of it is held."""
    return encode(RETIRE, _U32.pack(segment_id))


def parse_hello(body: bytes) -> tuple[int, str]:
    """(version, token) of a HELLO."""
    if len(body) < 2:
        raise ProtocolError("HELLO too short")
    return _U16.unpack_from(body)[0], body[2:].decode(errors="replace")


def parse_release(body: bytes) -> list[int]:
    """The value ids of a RELEASE."""
    if len(body) % 8:
        raise ProtocolError("RELEASE is not a whole number of u64 ids")
    return list(struct.unpack(f"<{len(body) // 8}Q", body))


def parse_received(body: bytes) -> tuple[int, int, bool]:
    """(call, count, ended) of a RECEIVED."""
    if len(body) != _RECEIVED.size:
        raise ProtocolError("RECEIVED has the wrong size")
    call, count, ended = _RECEIVED.unpack(body)
    return call, count, bool(ended)


def parse_welcome(body: bytes) -> tuple[int, bytes, bytes, int, int, int]:
    """(version, session, server id, threshold, window, staging size) of a WELCOME."""
    if len(body) != _WELCOME.size:
        raise ProtocolError("WELCOME has the wrong size")
    return _WELCOME.unpack(body)


def parse_segment(body: bytes) -> tuple[int, int]:
    """(segment id, size) of a SEGMENT."""
    if len(body) != _SEGMENT.size:
        raise ProtocolError("SEGMENT has the wrong size")
    return _SEGMENT.unpack(body)


def parse_retire(body: bytes) -> int:
    """The segment id of a RETIRE."""
    if len(body) != _U32.size:
        raise ProtocolError("RETIRE has the wrong size")
    return int(_U32.unpack(body)[0])


def send(sock: socket.socket, frame: bytes, fd: int | None = None) -> None:
    """Send one whole frame (with ``fd`` as SCM_RIGHTS); blocking sockets only."""
    if fd is None:
        sock.sendall(frame)
        return
    sent = sock.sendmsg([frame], [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array("i", [fd]))])
    if sent < len(frame):
        sock.sendall(frame[sent:])


_ANCILLARY = socket.CMSG_SPACE(16 * 4)  # room for the descriptors one read may bring
# A plain int: `flags & socket.MSG_CTRUNC` (an IntFlag) runs enum's machinery at every read.
_CTRUNC = int(socket.MSG_CTRUNC)


def _descriptors(ancillary: list[tuple[int, int, bytes]], flags: int) -> list[int]:
    """The memory files that came with one read; ProtocolError (each closed) if more came than it had room for."""
    fds: list[int] = []
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
            usable = len(payload) - len(payload) % 4
            fds.extend(array.array("i", payload[:usable]))
    if flags & _CTRUNC:
        for fd in fds:
            os.close(fd)
        raise ProtocolError("more memory files arrived than one read takes")
    return fds


def receive(sock: socket.socket, size: int = MAX_FRAME) -> tuple[bytes, list[int]]:
    """One ``recvmsg``: the bytes read (empty at the end) and the descriptors that came with them."""
    data, ancillary, flags, _ = sock.recvmsg(size, _ANCILLARY)
    return data, _descriptors(ancillary, flags)


class Inbox:
    """A buffer that one socket's reads go into, kept from read to read (one reader at a time).

    :func:`receive` makes a fresh bytes object of ``size`` for every read;
    past glibc's threshold (128 KiB) that is an ``mmap`` and a ``munmap`` each
    time, about 12 us on a warm machine, twice per frame for a reader that
    reads until the socket is empty (docs/performance-m8.md, "Cold caches, and
    the session's reads").
    """

    __slots__ = ("_view", "size")

    def __init__(self, size: int = MAX_FRAME) -> None:
        self.size = size
        self._view = memoryview(bytearray(size))

    def receive(self, sock: socket.socket) -> tuple[memoryview, list[int]]:
        """One ``recvmsg``, as :func:`receive`; the bytes are valid until the next read (feed them first).

        Fewer than :attr:`size` bytes: the socket held no more when read.
        """
        count, ancillary, flags, _ = sock.recvmsg_into([self._view], _ANCILLARY)
        return self._view[:count], _descriptors(ancillary, flags)


class FrameReader:
    """Bytes and descriptors in, whole frames out, each with the descriptor it carries."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._fds: deque[int] = deque()

    def feed(self, data: bytes | memoryview, fds: list[int]) -> list[Frame]:
        """Add what one read gave; the frames now complete."""
        self._buf += data
        self._fds.extend(fds)
        out: list[Frame] = []
        try:
            return self._frames(out)
        except ProtocolError:
            # The frames before the bad one are not handed out: their memory files go back, for stray() to close.
            self._fds.extendleft(reversed([frame.fd for frame in out if frame.fd is not None]))
            raise

    def _frames(self, out: list[Frame]) -> list[Frame]:
        """The complete frames in the buffer, appended to ``out`` as they are cut (taken off the buffer at the end)."""
        buf = self._buf
        at = 0
        while len(buf) - at >= 4:
            (length,) = _LEN.unpack_from(buf, at)
            if not 1 <= length <= MAX_WRITES_FRAME:
                raise ProtocolError(f"frame of {length} bytes (1 to {MAX_WRITES_FRAME} allowed)")
            if len(buf) - at < 5:
                break  # the kind decides the bound
            kind = buf[at + 4]
            limit = MAX_WRITES_FRAME if kind in LARGE else MAX_FRAME
            if length > limit:
                raise ProtocolError(
                    f"frame of kind {kind} has {length} bytes (1 to {limit} allowed"
                    + (": a write request over 64 MiB does not fit the Write stream either; stage large values)"
                       if kind in LARGE else ")")
                )
            if len(buf) - at - 4 < length:
                break
            body = bytes(buf[at + 5: at + 4 + length])
            at += 4 + length
            fd = None
            if kind in WITH_FD:
                if not self._fds:
                    raise ProtocolError(f"frame of kind {kind} came without its memory file")
                fd = self._fds.popleft()
            out.append(Frame(kind, body, fd))
        del buf[:at]
        return out

    def stray(self) -> list[int]:
        """Descriptors no frame claimed (to close)."""
        fds = list(self._fds)
        self._fds.clear()
        return fds
