"""The session of a component with every server it uses: Register, the Heartbeat stream, re-registration.

A session is what releases a component's locks and tasks when it goes away; it
reports the component's state at once when it changes, and after a broken
stream registers again with backoff (a new session). The server's answer to
Register says who the component is (the identity it verified from the token);
a launch environment that says otherwise is refused at start, naming both.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import grpc

from cast.client.channel import Backoff, LinkClosedError, ServerLink, map_rpc_error
from cast.client.credentials import TokenSource
from cast.core.records import Identity
from cast.core.sessions import ComponentState
from cast.errors import CastError, InvalidArgumentError
from cast.v1 import directory_pb2 as dir_pb2
from cast.version import library_version

__all__ = ["Session", "heartbeat_requests"]

log = logging.getLogger("cast.client")


def heartbeat_requests(
    server: ServerLink, closing: threading.Event, session_id: str, every: float, state: Callable[[], ComponentState]
) -> Iterator[dir_pb2.HeartbeatRequest]:
    """A Heartbeat stream's requests: one now, then one each ``every`` s or when asked; ends once ``closing`` is set.

    The client's close() sets ``closing``, then asks for a beat, which every
    generator sees, even one still read by gRPC for a stream that already
    ended: one waiting when the beat was asked is woken by it, and one that
    began after it sees ``closing`` before it waits.
    """
    asked = server.beats_asked()
    while True:
        yield dir_pb2.HeartbeatRequest(session_id=session_id, state=int(state()))  # type: ignore[arg-type]
        if closing.is_set():
            return
        asked = server.wait_beat(asked, every)
        if closing.is_set():
            return


class Session:
    """The sessions of one component with the servers it uses."""

    def __init__(
        self,
        identity: Identity,
        servers: Callable[[], Iterable[ServerLink]],
        call: Callable[..., Any],
        tokens: TokenSource,
        closing: threading.Event,
    ) -> None:
        self.identity = identity
        self._servers = servers
        self._call = call
        self._tokens = tokens
        self._closing = closing
        self.sessions = 0  # sessions registered so far (restarts and reconnects count)
        self.verified: Identity | None = None  # who the server said the component is

    def start(self, language: str, kind: str, state: Callable[[], ComponentState]) -> None:
        """Register with every server and keep the sessions alive with heartbeat streams.

        A broken session is registered again with backoff (a new session: the
        server released the locks and tasks of the old one when it ended).
        """
        for server in list(self._servers()):
            interval = self._register(server, language, kind)
            thread = threading.Thread(
                target=self._heartbeat, args=(server, interval, language, kind, state), name="cast-heartbeat",
                daemon=True,
            )
            thread.start()
            server.track(thread)

    def _register(self, server: ServerLink, language: str, kind: str) -> float:
        req = dir_pb2.RegisterRequest(
            language=language, kind=kind, pid=os.getpid(), host=socket.gethostname(),
            library_version=library_version(),
        )
        resp = self._call(server.directory.Register, req)
        self._check_identity(resp)
        server.session_id = resp.session_id
        server.registered.set()
        self.sessions += 1
        return float(max(0.05, resp.lease_ms / 3000))

    def _heartbeat(
        self, server: ServerLink, interval: float, language: str, kind: str, state: Callable[[], ComponentState]
    ) -> None:
        backoff = Backoff()
        while not self._closing.is_set():
            beats = heartbeat_requests(server, self._closing, server.session_id, interval, state)
            try:
                for _ in server.open_stream(server.directory.Heartbeat, beats, metadata=self._tokens.metadata()):
                    backoff.reset()
                if self._closing.is_set():
                    return
                reason = "the server ended the heartbeat stream"
            except grpc.RpcError as exc:
                if self._closing.is_set():
                    return
                reason = map_rpc_error(exc).message
            except LinkClosedError:  # the client closed before the stream could open
                return
            server.registered.clear()
            if server.shared is not None:
                server.shared.check()  # a server that died ended the shared-memory session too: unmap its memory now
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
        for server in self._servers():
            server.beat_now()

    def _check_identity(self, resp: dir_pb2.RegisterResponse) -> None:
        if not resp.component_id:
            return  # a server from before RegisterResponse said who the caller is
        verified = Identity(resp.component_id, resp.subarchitecture, resp.privileged)
        told = self.identity
        # An empty id or SA was not given (cast.connect with only a token): the server's answer fills it in.
        if (told.component_id and told.component_id != verified.component_id) or (
            told.subarchitecture and told.subarchitecture != verified.subarchitecture
        ):
            raise InvalidArgumentError(
                f"the token is for component '{verified.component_id}' in SA '{verified.subarchitecture}', but this "
                f"client was told component '{told.component_id}' in SA '{told.subarchitecture}' "
                "(CAST_COMPONENT_ID and CAST_SUBARCHITECTURE, or the connect options): give it the token issued "
                "for it (`cast token ID --subarchitecture SA`), or leave the id and SA to the token"
            )
        self.verified = verified
