"""Plain value types of the WM core: identities, entries, events, limits.

Entry records and events are immutable once made: a write makes a new record,
so an event can keep a reference to the record it reports without copying the
value, and readers can never see a record change under them.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import NamedTuple

from cast.core.arena import Placed

__all__ = [
    "BatchOp",
    "ChangeEvent",
    "EntryRecord",
    "Identity",
    "Limits",
    "LockMode",
    "Operation",
    "Quota",
    "SYSTEM_TYPES",
    "TASK_TYPE",
    "WriteResult",
    "no_session",
    "system_entry",
]


class Operation(enum.IntEnum):
    """Kind of a write; values equal the wire enum ``cast.v1.Operation``."""

    ADD = 1
    OVERWRITE = 2
    DELETE = 3


class LockMode(enum.IntEnum):
    """What a lock keeps other components from doing; values equal ``cast.v1.LockMode``."""

    O = 1
    OD = 2
    ODR = 3


class Identity(NamedTuple):
    """Who makes a call: taken from a verified token, never from a request field."""

    component_id: str
    subarchitecture: str
    privileged: bool = False

    def describe(self) -> str:
        """Human form used in error messages: ``component 'x' (SA 'vision')``."""
        sa = self.subarchitecture or "no SA"
        return f"component '{self.component_id}' (SA '{sa}')"


class BatchOp(NamedTuple):
    """One write of a batch: ``data``/``type`` are ignored for DELETE.

    ``placed``: the value is in the server's shared memory (``data`` is then
    its read-only view there; :mod:`cast.core.shared`).
    """

    operation: Operation
    subarchitecture: str
    id: str
    type: str = ""
    data: bytes | memoryview = b""
    expected_version: int | None = None
    placed: Placed | None = None


class WriteResult(NamedTuple):
    """Result of one write: the WM revision it made and the entry's new version."""

    revision: int
    version: int


class EntryRecord:
    """One entry as stored: never mutated after creation.

    ``data`` is bytes, or a read-only view of shared memory; ``shared`` then
    holds that memory for as long as the record lives (on the server the
    value's place in its arena, in a client the lease of a value it was lent).
    """

    __slots__ = ("author", "data", "id", "modified_ns", "revision", "shared", "size", "subarchitecture", "type",
                 "version")

    def __init__(
        self,
        subarchitecture: str,
        id: str,  # noqa: A002 - the wire name
        type: str,  # noqa: A002 - the wire name
        data: bytes | memoryview,
        version: int,
        author: str,
        modified_ns: int,
        revision: int,
        shared: object | None = None,
    ) -> None:
        self.subarchitecture = subarchitecture
        self.id = id
        self.type = type
        self.data = data
        self.version = version
        self.author = author
        self.modified_ns = modified_ns
        self.revision = revision
        self.shared = shared
        # The bytes it counts for against memory bounds (cast.core.room): its value and its id.
        self.size = len(data) + len(id)

    def __repr__(self) -> str:
        return (
            f"EntryRecord({self.subarchitecture}/{self.id}, type={self.type}, "
            f"version={self.version}, author={self.author}, revision={self.revision})"
        )


class ChangeEvent:
    """One change of one WM, as kept in its history ring and delivered to watchers.

    ``seq`` orders events across all WMs of a host; ``revision`` numbers them
    within their WM. ``entry`` is the record after the write (for DELETE, the
    record that was deleted). ``odr_holder`` is the component that held an ODR
    lock on the entry when it was written, so that other watchers are not sent
    its content.
    """

    __slots__ = (
        "entry",
        "first_skipped_revision",
        "id",
        "odr_holder",
        "operation",
        "revision",
        "seq",
        "skipped",
        "source_component",
        "source_subarchitecture",
        "subarchitecture",
        "time_ns",
        "type",
        "version",
        "wire",
    )

    def __init__(
        self,
        seq: int,
        revision: int,
        operation: Operation,
        subarchitecture: str,
        id: str,  # noqa: A002 - the wire name
        type: str,  # noqa: A002 - the wire name
        source_component: str,
        source_subarchitecture: str,
        version: int,
        time_ns: int,
        entry: EntryRecord | None,
        odr_holder: str | None = None,
    ) -> None:
        self.seq = seq
        self.revision = revision
        self.operation = operation
        self.subarchitecture = subarchitecture
        self.id = id
        self.type = type
        self.source_component = source_component
        self.source_subarchitecture = source_subarchitecture
        self.version = version
        self.time_ns = time_ns
        self.entry = entry
        self.odr_holder = odr_holder
        # Encoded forms cached by the transport layer (without, with the entry), so
        # that fan-out to many watchers encodes each event once.
        self.wire: list[bytes | None] | None = None
        # Set on the copy a latest-delivery watcher receives: the earlier changes of the entry it replaced
        # (cast.core.watch). Always 0 in the history.
        self.skipped = 0
        self.first_skipped_revision = 0

    def __repr__(self) -> str:
        return (
            f"ChangeEvent({self.operation.name} {self.subarchitecture}/{self.id} rev={self.revision} "
            f"v={self.version} type={self.type} by={self.source_component})"
        )


TASK_TYPE = "cast.v1.Task"
"""The type of the entries a task manager keeps of its tasks."""

SYSTEM_TYPES = frozenset({TASK_TYPE})
"""Types of entries the server itself writes: readable by all, written by no component."""


def system_entry(who: Identity, sa: str, entry_id: str, type_name: str, action: str) -> str:
    """Why ``who`` may not ``action`` a system entry, and what to do instead."""
    return (
        f"{who.describe()} may not {action} entry '{entry_id}' in subarchitecture '{sa}': {type_name} entries belong "
        f"to the server (the task manager of '{sa}' writes them); read or watch them, and use the task calls "
        "(propose, retract, complete) to change a task"
    )


def no_session(who: Identity, what: str) -> str:
    """Why ``who`` may not ``what`` without a session, and what to do."""
    return (
        f"{who.describe()} has no live session, so it may not {what}: locks and tasks end with the session that "
        "took them, and without one nothing would release them; register a session first (Directory.Register, "
        "then keep its Heartbeat stream open: the client libraries do this when a component starts)"
    )


@dataclass(frozen=True)
class Quota:
    """What one component may hold on a server, over all its WMs (0: no bound).

    A component holds the entries it wrote last: overwriting another's entry
    moves it (and its bytes) to the writer.
    """

    entries: int = 0
    bytes: int = 0


@dataclass(frozen=True)
class Limits:
    """Limits a server enforces; every refusal names the limit and how to change it."""

    max_id_bytes: int = 256
    max_type_bytes: int = 512
    max_value_bytes: int = 8 * 1024 * 1024
    max_entries: int = 10_000_000
    # Bytes of values and ids one WM may hold; 1 GiB fits the machines robots carry with a few SAs.
    max_total_bytes: int = 1 << 30
    history_events: int = 65_536
    history_bytes: int = 256 * 1024 * 1024
    max_watchers: int = 10_000
    max_lock_waiters: int = 10_000
    max_batch_operations: int = 10_000
