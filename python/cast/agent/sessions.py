"""One orchestrator's session for one system: its lease, and the events waiting to be delivered.

The session outlives its Attach stream by the lease: a cut link that comes
back within the lease re-attaches to the same session, keeps the processes
and receives every event it has not acknowledged. Events are numbered per
session; the orchestrator acknowledges them on its keepalives, and only
unacknowledged ones are kept, at most :data:`MAX_BUFFERED` (the oldest output
lines and samples go first; exits are never dropped, since the orchestrator
supervises by them).
"""

from __future__ import annotations

import asyncio
import time
from collections import deque

from cast.v1 import agent_pb2

__all__ = ["DEFAULT_GRACE_MS", "DEFAULT_LEASE_MS", "MAX_BUFFERED", "SystemSession"]

DEFAULT_LEASE_MS = 10_000
DEFAULT_GRACE_MS = 3_000
MAX_BUFFERED = 10_000


class SystemSession:
    """The session of one system: lease, event buffer, and which stream (if any) is attached."""

    def __init__(self, system: str, lease_ms: int, grace_ms: int) -> None:
        self.system = system
        self.lease_s = (lease_ms or DEFAULT_LEASE_MS) / 1000
        self.grace_s = (grace_ms or DEFAULT_GRACE_MS) / 1000
        self._deadline = time.monotonic() + self.lease_s
        self._events: deque[agent_pb2.AgentEvent] = deque()
        self._seq = 0
        self._wakeup = asyncio.Event()
        self.stream = 0  # id of the attached stream; 0 while detached
        self._streams = 0
        self.ended = False

    # ---------------------------------------------------------------- lease

    def touch(self) -> None:
        """The orchestrator was heard from: the lease starts again."""
        self._deadline = time.monotonic() + self.lease_s

    @property
    def expired(self) -> bool:
        """Whether the lease ran out (checked by the agent's reaper)."""
        return time.monotonic() > self._deadline

    # --------------------------------------------------------------- streams

    def attach(self) -> int:
        """A new stream takes the session over; returns its id (an older stream sees it is replaced)."""
        self._streams += 1
        self.stream = self._streams
        self.touch()
        self._wakeup.set()  # an older stream waiting for events notices it was replaced
        return self.stream

    def detach(self, stream: int) -> None:
        """The stream ``stream`` ended; the lease counts from now."""
        if self.stream == stream:
            self.stream = 0
            self.touch()
            self._wakeup.set()  # the stream's sender, waiting for events, ends

    @property
    def attached(self) -> bool:
        """Whether a stream is attached now."""
        return self.stream != 0

    def end(self) -> None:
        """The session is over (lease expired, agent stopping): wake any stream so that it closes."""
        self.ended = True
        self.stream = 0
        self._wakeup.set()

    # ---------------------------------------------------------------- events

    def push(self, event: agent_pb2.AgentEvent) -> None:
        """Number ``event`` and queue it for delivery."""
        self._seq += 1
        event.seq = self._seq
        self._events.append(event)
        if len(self._events) > MAX_BUFFERED:
            self._drop_oldest()
        self._wakeup.set()

    def _drop_oldest(self) -> None:
        for index, queued in enumerate(self._events):
            if not queued.HasField("exit"):
                del self._events[index]
                return

    def ack(self, seq: int) -> None:
        """Forget every event up to ``seq``: the orchestrator has it."""
        while self._events and self._events[0].seq <= seq:
            self._events.popleft()

    def after(self, seq: int) -> list[agent_pb2.AgentEvent]:
        """The buffered events numbered above ``seq``, oldest first."""
        return [e for e in self._events if e.seq > seq]

    async def wait(self, stream: int, seq: int) -> list[agent_pb2.AgentEvent] | None:
        """The events after ``seq`` once there are some; None once ``stream`` is replaced or the session ended."""
        while True:
            if self.ended or self.stream != stream:
                return None
            events = self.after(seq)
            if events:
                return events
            self._wakeup.clear()
            await self._wakeup.wait()
