"""Large values by shared memory on one host: the rules, the sessions of clients, and what it counts.

Values of at least ``shared_memory.threshold_bytes`` are kept in the server's
arena (:mod:`cast.core.arena`), however they arrived. A client on the server's
host opens a *session* on the server's Unix socket (the transport is the
server's, :mod:`cast.server.shared_socket`); the session has

- a *staging area*: a memory file the client writes values into; a write
  names the bytes there (``StagedValue``) instead of carrying them, and the
  server copies them into the arena before the write is applied, so nothing
  the writer does later changes what readers see;
- *leases*: the values the server sent it by reference (events, reads) and
  it has not given back. A value lent is never overwritten; at most
  ``shared_memory.window_bytes`` are lent to one session at once, and past
  that values go to it as bytes. A call's references that never reached the
  client (its stream broke) are given back when the client says how many it
  received (:meth:`SharedMemory.received`); a session that ends gives back
  everything.

Every refusal here names what was wrong and what to do, and changes nothing.
Plain Python: no gRPC, no sockets (docs/design.md section 2).
"""

from __future__ import annotations

import collections
import mmap
import os
import secrets
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

from cast.core.arena import Arena, Placed, Segment, memory_file, round_up
from cast.core.records import BatchOp, Identity, Limits, Operation
from cast.errors import InvalidArgumentError, PermissionDeniedError

__all__ = ["Lent", "SharedMemory", "SharedSession", "SharedSettings"]

SEGMENT_BYTES = 64 << 20
"""A segment's size: 64 MiB, or twice ``limits.max_value_bytes`` when that is more."""

MAX_OPEN_CALLS = 4096
"""Calls of one session with references not yet accounted for; past this the oldest is taken as ended."""


@dataclass(frozen=True)
class SharedSettings:
    """The ``shared_memory:`` section of a configuration (docs/client-protocol.md, "Large values by shared memory")."""

    enabled: bool = True
    # Below this a value's bytes cost less to copy through gRPC than to place, lend and give back.
    threshold_bytes: int = 64 * 1024
    # The arena's segments take at most this much memory (virtual until used); values past it travel as bytes.
    max_bytes: int = 1 << 30
    # What one client session may hold lent at once; past it, values go to that client as bytes.
    window_bytes: int = 64 << 20


class Lent:
    """Where a lent value is, as a ``SharedValue`` says it."""

    # A class, not a NamedTuple: one is made per value lent to each reader, on the write's path, and compiled (the
    # compiled build) it is made in C, where a NamedTuple's __new__ is Python code (docs/performance-m8.md).
    __slots__ = ("offset", "segment", "size", "value_id")

    def __init__(self, segment: int, offset: int, size: int, value_id: int) -> None:
        self.segment = segment
        self.offset = offset
        self.size = size
        self.value_id = value_id

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Lent) and (self.segment, self.offset, self.size, self.value_id) == (
            other.segment, other.offset, other.size, other.value_id)

    def __hash__(self) -> int:
        return hash((self.segment, self.offset, self.size, self.value_id))

    def __repr__(self) -> str:
        return f"Lent(segment={self.segment}, offset={self.offset}, size={self.size}, value_id={self.value_id})"


class _Call:
    """The references sent on one call of a session, oldest first, until the client confirms it received them."""

    __slots__ = ("confirmed", "sent")

    def __init__(self) -> None:
        self.sent: collections.deque[int] = collections.deque()
        self.confirmed = 0  # how many the client said it received so far (popped from ``sent``)


class FrameLink(Protocol):
    """The transport's connection of one session (:mod:`cast.server.shared_socket`): frames to its client."""

    @property
    def closed(self) -> bool:
        """Whether the connection ended (nothing more is sent)."""
        ...

    @property
    def unsent(self) -> int:
        """Bytes of frames waiting for room in the socket (the client has not read them)."""
        ...

    def send(self, frame: bytes, fd: int | None = None) -> bool:
        """Send a frame now or as soon as there is room, in order; False once closed."""
        ...

    def listen(self, fn: Callable[[], None]) -> Callable[[], None]:
        """Call ``fn`` when the connection closes or its unsent bytes went out; returns what stops it."""
        ...


class SharedSession:
    """One client's session: who it is, its staging area, and what it holds lent."""

    def __init__(self, who: Identity, staging_bytes: int) -> None:
        self.id = secrets.token_bytes(16)
        self.who = who
        self.staging_bytes = staging_bytes
        self.staging_fd = memory_file("cast-staging", staging_bytes)
        try:
            # Read-only: the server only copies out of it (and never trusts it twice: it copies, then checks the copy).
            self.staging = mmap.mmap(self.staging_fd, staging_bytes, prot=mmap.PROT_READ)
        except BaseException:
            os.close(self.staging_fd)
            raise
        self.leases: dict[int, list[int]] = {}  # value id -> [leases, bytes of one]
        self.lent_bytes = 0
        self.calls: dict[int, _Call] = {}
        self.segments: set[int] = set()  # segments whose memory file this client was sent
        # The transport's: send a segment's SEGMENT frame to this client; False if it could not.
        self.send_segment: Callable[[Segment], bool] | None = None
        # The transport's connection to this client, for frames other than segments (a watch's events).
        self.link: FrameLink | None = None
        self.closed = False

    def forget_staging_fd(self) -> None:
        """Close the staging area's descriptor once the client has it (the mapping keeps the memory file)."""
        if self.staging_fd >= 0:
            os.close(self.staging_fd)
            self.staging_fd = -1

    def describe(self) -> str:
        """How messages name it: ``shared-memory session ab12... of component 'x'``."""
        return f"shared-memory session {self.id.hex()} of component '{self.who.component_id}'"


class SharedMemory:
    """The shared memory of one server: its arena, the sessions of its clients, what went through it."""

    def __init__(self, settings: SharedSettings, limits: Limits) -> None:
        self.settings = settings
        self.limits = limits
        self.server_id = secrets.token_hex(16)
        self.arena = Arena(settings.max_bytes, max(SEGMENT_BYTES, 2 * limits.max_value_bytes))
        # Room for two of the largest values: a writer stages the next while the last is being applied.
        self.staging_bytes = round_up(2 * limits.max_value_bytes)
        self.sessions: dict[bytes, SharedSession] = {}
        self._lock = threading.Lock()  # the counters and the session table: writes come from in-process threads too
        self.staged_writes = self.staged_bytes = 0
        self.lent = self.lent_total_bytes = 0
        self.unplaced = self.over_window = 0

    # ------------------------------------------------------------------ values

    def place(self, op: BatchOp) -> BatchOp:
        """``op`` with its value in the arena when it is large enough; unchanged otherwise.

        Values over ``limits.max_value_bytes`` are left for the write's own
        check to refuse; a full arena leaves the value where it is (bytes).
        """
        if op.placed is not None or op.operation is Operation.DELETE:
            return op
        size = len(op.data)
        if size < self.settings.threshold_bytes or size > self.limits.max_value_bytes:
            return op
        placed = self.arena.put(op.data)
        if placed is None:
            with self._lock:
                self.unplaced += 1
            return op
        return op._replace(data=placed.view, placed=placed)

    def staged(
        self, who: Identity, session_id: bytes, offset: int, size: int, entry_id: str
    ) -> tuple[bytes | memoryview, Placed | None]:
        """The bytes a write staged, copied out of its writer's staging area: (its data, where it was placed).

        Only the writer's own session may be named. The copy is taken before
        the write is checked or applied, and the check reads the copy: what
        the writer does to its staging area afterwards changes nothing.
        """
        session = self.sessions.get(bytes(session_id))
        if session is None or session.closed:
            raise InvalidArgumentError(
                f"the value of entry '{entry_id}' is staged in shared-memory session "
                f"{bytes(session_id).hex() or '(none)'}, which this server does not have (it ended, or the server "
                "restarted): send the value's bytes (value.value), or stage it again in a live session"
            )
        if session.who.component_id != who.component_id:
            raise PermissionDeniedError(
                f"{who.describe()} may not use the {session.describe()}: a component stages its values in its "
                "own session"
            )
        if size > self.limits.max_value_bytes:
            raise InvalidArgumentError(
                f"value of entry '{entry_id}' is {size} bytes, over the limit of {self.limits.max_value_bytes} "
                "bytes (limits.max_value_bytes): store large data elsewhere and keep a reference, or raise the "
                "limit in the configuration"
            )
        if offset < 0 or size < 0 or offset + size > session.staging_bytes:
            raise InvalidArgumentError(
                f"the value of entry '{entry_id}' is staged at offset {offset}, {size} bytes: outside the staging "
                f"area of {session.staging_bytes} bytes of the {session.describe()}"
            )
        source = memoryview(session.staging)[offset: offset + size]
        try:
            placed = self.arena.put(source) if size else None
            data: bytes | memoryview = placed.view if placed is not None else bytes(source)
        finally:
            source.release()
        with self._lock:
            self.staged_writes += 1
            self.staged_bytes += size
            if placed is None and size:
                self.unplaced += 1
        return data, placed

    # ---------------------------------------------------------------- sessions

    def open_session(self, who: Identity) -> SharedSession:
        """A new session for ``who`` (the identity its token gave), with its staging area."""
        session = SharedSession(who, self.staging_bytes)
        with self._lock:
            self.sessions[session.id] = session
        return session

    def close_session(self, session: SharedSession) -> None:
        """End a session: everything it holds is given back, its staging area unmapped."""
        with self._lock:
            if session.closed:
                return
            session.closed = True
            self.sessions.pop(session.id, None)
        for value_id, (count, _) in session.leases.items():
            self.arena.give_back([value_id] * count)
        session.leases.clear()
        session.calls.clear()
        session.lent_bytes = 0
        session.staging.close()
        session.forget_staging_fd()

    def session_for(self, who: Identity, session_id: bytes) -> SharedSession | None:
        """The session a read names (None when this server has none by that id: the read then gets bytes).

        PERMISSION_DENIED when it is another component's: values are lent to
        the session they are read for, and nobody may spend another's window.
        """
        session = self.sessions.get(session_id)
        if session is None or session.closed:
            return None
        if session.who.component_id != who.component_id:
            raise PermissionDeniedError(
                f"{who.describe()} named the {session.describe()} in its cast-shared-memory metadata: name your own "
                "session (the one your WELCOME frame gave), or none"
            )
        return session

    # ------------------------------------------------------------------ leases

    def lend(self, session: SharedSession, call: int, placed: Placed) -> Lent | None:
        """Lend ``placed`` to ``session`` on its call ``call``; None (send the bytes) past its window, or once gone."""
        if session.closed:
            return None
        length = placed.length
        if session.lent_bytes and session.lent_bytes + length > self.settings.window_bytes:
            with self._lock:
                self.over_window += 1
            return None
        segment_id = placed.segment
        if segment_id not in session.segments:
            segment = self.arena.segment(segment_id)
            if segment is None or session.send_segment is None or not session.send_segment(segment):
                return None
            session.segments.add(segment_id)
        self.arena.lease(placed)
        value_id = placed.value_id
        held = session.leases.get(value_id)
        if held is None:
            session.leases[value_id] = [1, length]
        else:
            held[0] += 1
        session.lent_bytes += length
        calls = session.calls
        record = calls.get(call)
        if record is None:
            if len(calls) >= MAX_OPEN_CALLS:
                self.received(session, next(iter(calls)), 0, True)
            record = calls[call] = _Call()
        record.sent.append(value_id)
        with self._lock:
            self.lent += 1
            self.lent_total_bytes += length
        return Lent(segment_id, placed.offset, length, value_id)

    def give_back(self, session: SharedSession, value_ids: Iterable[int]) -> None:
        """End one of the session's leases of each value named (RELEASE); ids it does not hold are ignored."""
        ended = []
        for value_id in value_ids:
            held = session.leases.get(value_id)
            if held is None:
                continue
            held[0] -= 1
            session.lent_bytes -= held[1]
            if not held[0]:
                del session.leases[value_id]
            ended.append(value_id)
        if ended:
            self.arena.give_back(ended)

    def received(self, session: SharedSession, call: int, count: int, ended: bool) -> None:
        """The client received ``count`` references on ``call`` so far (RECEIVED); ``ended``: the call is over.

        The references sent on an ended call past the first ``count`` never
        reached it (the stream broke first): they are given back here.
        """
        record = session.calls.get(call)
        if record is None:
            return
        sent = record.sent
        while record.confirmed < count and sent:
            sent.popleft()
            record.confirmed += 1
        if ended:
            del session.calls[call]
            self.give_back(session, list(sent))

    def retire_empty(self) -> list[int]:
        """Retire the segments left empty (:meth:`Arena.retire_empty`); sessions forget them."""
        retired = self.arena.retire_empty()
        for session in list(self.sessions.values()):
            session.segments.difference_update(retired)
        return retired

    def close(self) -> None:
        """End every session and close the arena (the server is stopping)."""
        for session in list(self.sessions.values()):
            self.close_session(session)
        self.arena.close()

    # ------------------------------------------------------------------- state

    def snapshot(self) -> dict[str, int]:
        """What is in shared memory now and what went through it (``cast stats``; docs/experiments.md)."""
        out = self.arena.stats()
        with self._lock:
            out.update(
                sessions=len(self.sessions), staged_writes=self.staged_writes, staged_bytes=self.staged_bytes,
                lent=self.lent, lent_total_bytes=self.lent_total_bytes, unplaced=self.unplaced,
                over_window=self.over_window, max_bytes=self.settings.max_bytes,
                threshold_bytes=self.settings.threshold_bytes,
            )
        return out
