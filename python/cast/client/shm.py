"""Large values by shared memory with a server on this host: is there a session (docs/client-protocol.md).

Each server link has a :class:`SharedLink`. On first need it asks the server
where its shared memory is (``SystemDescription.shared_memory``), connects to
that Unix socket (abstract namespace: only reachable from the server's host),
checks that the server runs as this process's OS user, says HELLO with the
token and gets WELCOME: a session id, the staging area (a memory file) and the
threshold. If any of that fails, the link says why once at INFO and values
travel as bytes; ``CAST_SHARED_MEMORY=off`` in the environment turns it off.

The session itself is :class:`cast.client.shm_session.ClientSession`.
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from cast.client.credentials import TokenSource
from cast.client.shm_session import ClientSession, ReadCall
from cast.client.write_replies import DRAIN_S
from cast.v1 import directory_pb2 as dir_pb2
from cast.wire import shared_memory as wire

if TYPE_CHECKING:
    from cast.client.channel import ServerLink

__all__ = ["ENV", "SharedLink", "Unreachable", "attach", "connect", "turned_off"]

log = logging.getLogger("cast.client")

ENV = "CAST_SHARED_MEMORY"
"""``off`` (or ``0``, ``false``, ``no``) in a process's environment: it never uses shared memory."""

_CONNECT_S = 2.0  # the handshake's bound
# How long asking a server where its shared memory is may take: it is asked on the way of a write or a watch.
_DESCRIBE_S = 5.0
_RETRY_S = 5.0  # how long after a failure the link tries again
_RETRY_ELSEWHERE_S = 60.0  # ... when the server is elsewhere or offers none (a restart of it may change that)
_UCRED = struct.Struct("3i")


def turned_off() -> bool:
    """Whether this process's environment turns shared memory off (:data:`ENV`)."""
    return os.environ.get(ENV, "").strip().lower() in ("off", "0", "false", "no")


class Unreachable(ValueError):
    """The server's socket cannot be reached from here: it is on another host or in another network namespace."""


def connect(info: dir_pb2.SharedMemoryInfo, token: str, endpoint: str, within: float = _CONNECT_S) -> ClientSession:
    """Open a session with the server whose shared memory ``info`` names, in ``within`` seconds at most.

    OSError or ValueError saying why not.
    """
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    try:
        end = time.monotonic() + within
        sock.settimeout(within)
        try:
            sock.connect("\0" + info.socket)
        except (FileNotFoundError, ConnectionRefusedError) as exc:
            raise Unreachable(f"its socket is not reachable from here ({exc.strerror}): another host or network "
                              "namespace") from None
        pid, uid, _ = _UCRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, _UCRED.size))
        if uid != os.geteuid():
            raise ValueError(f"the process behind its socket ({pid}) runs as OS user {uid}, this one as "
                             f"{os.geteuid()}")
        wire.send(sock, wire.hello(token))
        reader = wire.FrameReader()
        while True:
            sock.settimeout(max(0.001, end - time.monotonic()))
            data, fds = wire.receive(sock)
            if not data:
                raise ValueError("the server closed the connection after HELLO")
            frames = reader.feed(data, fds)
            if frames:
                break
            if time.monotonic() > end:
                raise ValueError(f"no WELCOME within {within:g} s")
        first = frames[0]
        for fd in reader.stray() + [f.fd for f in frames[1:] if f.fd is not None]:
            os.close(fd)
        if first.kind == wire.REFUSED:
            raise ValueError(f"refused: {first.body.decode(errors='replace')}")
        if first.kind != wire.WELCOME or first.fd is None:
            raise ValueError(f"answered HELLO with a frame of kind {first.kind}")
        sock.setblocking(False)
        session = ClientSession(sock, first.body, first.fd, endpoint, token)
        session.reads = info.reads
        if session.server_id != info.server_id:
            session.close()
            raise ValueError(f"its socket belongs to another server (id {session.server_id}, not "
                             f"{info.server_id})")
        return session
    except BaseException:
        sock.close()
        raise


def attach(link: ServerLink, tokens: TokenSource, call: Callable[..., Any]) -> SharedLink:
    """Give ``link`` shared memory with its server, opened when first needed.

    ``call(method, request, timeout=)`` makes a call with the caller's credentials: the one that asks the
    server where its shared memory is.
    """

    def describe(within: float | None) -> dir_pb2.SystemDescription:
        # The server itself says where its shared memory is: ask it, not the directory.
        timeout = _DESCRIBE_S if within is None else min(_DESCRIBE_S, within)
        desc: dir_pb2.SystemDescription = call(link.directory.DescribeSystem, dir_pb2.DescribeSystemRequest(),
                                               timeout=timeout)
        return desc

    link.shared = SharedLink(link.endpoint, tokens, describe)
    return link.shared


class SharedLink:
    """Shared memory with one server for one client: the session, opened when first needed, or why there is none."""

    def __init__(self, endpoint: str, tokens: TokenSource,
                 describe: Callable[[float | None], dir_pb2.SystemDescription]) -> None:
        self.endpoint = endpoint
        self._tokens = tokens
        self._describe = describe
        self._lock = threading.Lock()
        self._session: ClientSession | None = None
        self._retry_at = 0.0
        self._told = False  # the fallback was said at INFO
        self.reason = ""  # why values travel as bytes, while they do
        self._closed = False

    def session(self, within: float | None = None, token: str | None = None) -> ClientSession | None:
        """The live session, opened now if none is (at most every few seconds after a failure); None: bytes.

        ``within``: the longest opening it may take (a call's time left), waiting for another thread's opening
        included (past it, bytes); None: its own bounds. ``token``: a writer's current token; a session opened
        with another (the token was renewed) is ended after its outstanding writes and a new one opened, since a
        session's identity is its HELLO's token and a write's staged value must be in the session it goes on.
        """
        session = self._session
        if session is not None and not session.dead:
            if token is None or session.token == token:
                return session
            self.renew(DRAIN_S)
        if self._closed or time.monotonic() < self._retry_at:
            return None
        started = time.monotonic()
        if not self._lock.acquire(timeout=-1 if within is None else within):
            return None
        try:
            session = self._session
            if session is not None and not session.dead:
                return session
            if self._closed or time.monotonic() < self._retry_at:
                return None
            left = None if within is None else within - (time.monotonic() - started)
            if left is not None and left <= 0:
                return None
            self._session = self._open(left)
            return self._session
        finally:
            self._lock.release()

    def _open(self, within: float | None) -> ClientSession | None:
        if turned_off():
            self._fallback(f"turned off by {ENV}={os.environ.get(ENV)}", forever=True)
            return None
        try:
            started = time.monotonic()
            info = self._describe(within).shared_memory
        except Exception as exc:  # noqa: BLE001 - any failure of the question is a reason to use bytes
            self._fallback(f"the server did not say where it is: {exc}")
            return None
        if not info.socket:
            self._fallback("the server offers none (shared_memory.enabled is false there)", _RETRY_ELSEWHERE_S)
            return None
        try:
            left = _CONNECT_S if within is None else min(_CONNECT_S, within - (time.monotonic() - started))
            if left <= 0:
                raise ValueError("no time left in the call that asked for it")
            session = connect(info, self._tokens.token(), self.endpoint, left)
        except Unreachable as exc:
            self._fallback(str(exc), _RETRY_ELSEWHERE_S)
            return None
        except (OSError, ValueError, wire.ProtocolError) as exc:
            self._fallback(str(exc))
            return None
        self.reason = ""
        log.debug("values of at least %d bytes travel by shared memory with %s", session.threshold, self.endpoint)
        return session

    def _fallback(self, reason: str, retry_s: float = _RETRY_S, forever: bool = False) -> None:
        self.reason = reason
        self._retry_at = float("inf") if forever else time.monotonic() + retry_s
        if not self._told:
            self._told = True
            log.info("shared memory with the server at %s is not used (%s): values travel as bytes",
                     self.endpoint, reason)

    @contextmanager
    def read(self, within: float | None = None, token: str | None = None) -> Iterator[ReadCall | None]:
        """A read call's session part (None without a session): its metadata, and its end when the call is over.

        ``within``: the longest opening the session may take; ``token``: the
        reader's current token, for a read sent on the session's socket (see
        :meth:`session`).
        """
        session = self.session(within, token)
        call = session.new_call() if session is not None else None
        answered = False
        try:
            yield call
            answered = True
        finally:
            if call is not None:
                call.end(answered)

    def current(self) -> ClientSession | None:
        """The session open now, if any (none is opened)."""
        session = self._session
        return session if session is not None and not session.dead else None

    def renew(self, drain_s: float) -> None:
        """End the session after its outstanding writes (``drain_s`` at most): the token was renewed.

        A session's identity is its HELLO's token, so the next write opens a
        new one with the new token, and no write of the new one overtakes the
        old one's.
        """
        with self._lock:
            session, self._session = self._session, None
        if session is not None:
            session.writes.drain(drain_s)
            session.close()

    def check(self) -> None:
        """Read what the server sent; a session it ended is noticed now (a stream to it broke)."""
        session = self._session
        if session is not None:
            session.poll()

    def close(self) -> None:
        """End the session."""
        self._closed = True
        session, self._session = self._session, None
        if session is not None:
            session.close()
