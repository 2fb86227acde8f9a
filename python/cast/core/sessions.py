"""Component sessions: who is connected, and what happens when a component goes away.

A component registers and then keeps its session alive with heartbeats. When
the session ends (the heartbeat stream closes, the lease runs out, or the
component registers again after a restart), ``on_end`` is called with the
component id: the server releases its locks and retracts its tasks there.
"""

from __future__ import annotations

import enum
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

from cast.core.records import Identity
from cast.errors import InvalidArgumentError, NotFoundError, PermissionDeniedError

__all__ = ["ComponentInfo", "ComponentState", "SessionStream", "SessionTable"]


class ComponentState(enum.IntEnum):
    """Values equal the wire enum ``cast.v1.ComponentState``."""

    EXPECTED = 1
    STARTING = 2
    RUNNING = 3
    STOPPING = 4
    DISCONNECTED = 5
    STARTED = 6  # start() returned, watches registered; run() waits for the start barrier


@dataclass
class ComponentInfo:
    """What the directory knows of one component."""

    id: str
    subarchitecture: str
    privileged: bool = False
    language: str = ""
    kind: str = ""
    state: ComponentState = ComponentState.EXPECTED
    session_id: str = ""
    pid: int = 0
    host: str = ""
    sessions: int = 0
    library_version: str = ""  # the client library's release, as it registered ("": it did not say)
    placed_on: str = ""  # the host the configuration places it on (hosts:); shown instead of the one it reports
    deadline: float = 0.0  # monotonic time the lease ends


class SessionTable:
    """Sessions of the components of one server."""

    def __init__(
        self,
        on_end: Callable[[str], None],
        lease_ms: int = 10_000,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._on_end = on_end
        self.lease_ms = lease_ms
        self._clock = clock
        self._mutex = threading.Lock()
        self._components: dict[str, ComponentInfo] = {}
        self._sessions: dict[str, str] = {}  # session id -> component id

    def expect(self, info: ComponentInfo) -> None:
        """Record a component named in the configuration, before it connects."""
        with self._mutex:
            self._components.setdefault(info.id, info)

    def register(
        self, who: Identity, language: str, kind: str, pid: int, host: str, library_version: str = ""
    ) -> str:
        """Start a session for ``who``; a previous session of the same component ends first."""
        with self._mutex:
            info = self._components.get(who.component_id)
            old = info.session_id if info is not None else ""
            if info is None:
                info = ComponentInfo(who.component_id, who.subarchitecture, who.privileged)
                self._components[who.component_id] = info
            if old:
                self._sessions.pop(old, None)
        if old:
            # The component restarted: whatever its old incarnation held is stale.
            self._on_end(who.component_id)
        session_id = secrets.token_hex(8)
        with self._mutex:
            info.subarchitecture, info.privileged = who.subarchitecture, who.privileged
            info.language, info.kind, info.pid = language, kind, pid
            info.library_version = library_version
            info.host = info.placed_on or host
            info.session_id, info.state = session_id, ComponentState.STARTING
            info.sessions += 1
            info.deadline = self._clock() + self.lease_ms / 1000
            self._sessions[session_id] = who.component_id
        return session_id

    def heartbeat(self, who: Identity, session_id: str, state: ComponentState | None = None) -> None:
        """Renew a session's lease and record the component's state."""
        with self._mutex:
            component_id = self._sessions.get(session_id)
            if component_id is None:
                raise NotFoundError(f"no session '{session_id}': it ended; register again")
            if component_id != who.component_id:
                raise PermissionDeniedError(
                    f"session '{session_id}' belongs to '{component_id}', not to {who.describe()}"
                )
            info = self._components[component_id]
            info.deadline = self._clock() + self.lease_ms / 1000
            if state is not None and state not in (ComponentState.EXPECTED, ComponentState.DISCONNECTED):
                info.state = state

    def end(self, session_id: str) -> bool:
        """End a session (its stream closed); False if it had already ended."""
        with self._mutex:
            component_id = self._sessions.pop(session_id, None)
            if component_id is None:
                return False
            info = self._components[component_id]
            info.session_id, info.state = "", ComponentState.DISCONNECTED
        self._on_end(component_id)
        return True

    def expire(self) -> list[str]:
        """End every session whose lease has run out; return their component ids."""
        now = self._clock()
        with self._mutex:
            stale = [s for s, c in self._sessions.items() if self._components[c].deadline < now]
        ended = []
        for session_id in stale:
            component_id = self._sessions.get(session_id)
            if component_id is not None and self.end(session_id):
                ended.append(component_id)
        return ended

    def has_live(self, component_id: str) -> bool:
        """Whether a component has a live session (it may take locks and propose tasks)."""
        with self._mutex:
            info = self._components.get(component_id)
            return info is not None and bool(info.session_id) and info.session_id in self._sessions

    def is_live(self, session_id: str) -> bool:
        """Whether a session is still live."""
        with self._mutex:
            return session_id in self._sessions

    def components(self) -> list[ComponentInfo]:
        """A snapshot of every known component, in the order first seen."""
        with self._mutex:
            return [replace(info) for info in self._components.values()]


class SessionStream:
    """One heartbeat stream of one caller: the one session it keeps alive, which ends with the stream.

    Over gRPC this is a ``Directory.Heartbeat`` call; in process, the in-process transport's timer
    thread. Either way the session ends when the stream ends (:meth:`end`), releasing the component's
    locks and tasks.
    """

    def __init__(self, table: SessionTable, who: Identity) -> None:
        self._table = table
        self._who = who
        self._session_id = ""

    def beat(self, session_id: str, state: ComponentState | None) -> int:
        """Renew ``session_id`` with ``state``; the lease (ms) until the next beat is due.

        INVALID_ARGUMENT for a second session on one stream. The session is checked before the
        stream adopts it: a stream that names another component's session must not end that
        session when it is refused.
        """
        if self._session_id and session_id != self._session_id:
            raise InvalidArgumentError("one heartbeat stream serves one session")
        self._table.heartbeat(self._who, session_id, state)
        self._session_id = session_id
        return self._table.lease_ms

    def end(self) -> None:
        """The stream ended (the component left, or its connection broke): end its session."""
        if self._session_id:
            self._table.end(self._session_id)
            self._session_id = ""
