"""The values a component reads: an entry's address, an entry, a change event, a task.

Each decodes its value into the caller's class on demand, and turns bytes that
do not parse into :class:`cast.InvalidArgumentError` naming the entry (C++:
``types.h``; Java: ``Entry``, ``WorkingMemoryChange``, ``Task``).
"""

from __future__ import annotations

import builtins
from dataclasses import dataclass
from operator import attrgetter
from typing import TYPE_CHECKING, Generic, NamedTuple, TypeVar

from google.protobuf.message import DecodeError, Message

from cast.core.records import ChangeEvent, EntryRecord
from cast.core.tasks import TaskRecord
from cast.errors import InvalidArgumentError

if TYPE_CHECKING:
    from cast.client.views import ValueView

__all__ = ["Entry", "Task", "WorkingMemoryAddress", "WorkingMemoryChange", "decode", "entry_of"]

M = TypeVar("M", bound=Message)


class WorkingMemoryAddress(NamedTuple):
    """Where an entry lives."""

    id: str
    subarchitecture: str


def decode(cls: type[M], type_name_: str, data: bytes | memoryview, what: str) -> M:
    """The value as ``cls``: InvalidArgumentError for another type, or for bytes that do not parse."""
    expected = cls.DESCRIPTOR.full_name
    if type_name_ != expected:
        raise InvalidArgumentError(f"{what} has type {type_name_}, not {expected}: read it with the right class")
    try:
        return cls.FromString(data)  # type: ignore[arg-type]  # upb parses any buffer: shared memory too
    except (DecodeError, RuntimeError) as exc:
        # A value stored corrupt (or with another schema) is the caller's error to see, not a protobuf crash.
        raise InvalidArgumentError(
            f"{what} does not parse as {expected} ({exc}): it was written corrupt or with another schema; "
            "overwrite or delete it"
        ) from None


@dataclass(frozen=True)
class Entry(Generic[M]):
    """An entry read from a WM: its value (a fresh copy) and its metadata."""

    address: WorkingMemoryAddress
    type: str
    value: M
    version: int
    author: str
    revision: int
    modified_ns: int

    @property
    def id(self) -> str:
        """The entry's id."""
        return self.address.id


def entry_of(cls: type[M], record: EntryRecord) -> Entry[M]:
    """An entry record as an :class:`Entry` of ``cls``."""
    return Entry(
        WorkingMemoryAddress(record.id, record.subarchitecture),
        record.type,
        decode(cls, record.type, record.data, f"entry '{record.id}' in subarchitecture '{record.subarchitecture}'"),
        record.version,
        record.author,
        record.revision,
        record.modified_ns,
    )


class WorkingMemoryChange:
    """One change event as delivered to an ``on_change`` callback."""

    __slots__ = ("_ev", "first_skipped_revision", "skipped")

    def __init__(self, event: ChangeEvent) -> None:
        self._ev = event
        self.skipped: int = event.skipped
        """For a ``delivery="latest"`` watch: how many earlier changes of this entry it replaced (0: none)."""
        self.first_skipped_revision: int = event.first_skipped_revision
        """The revision of the oldest change it replaced (0: none)."""

    def replacing(self, older: WorkingMemoryChange) -> WorkingMemoryChange:
        """This change, counting ``older`` (and what it replaced) as skipped: conflation in the client's queue."""
        self.skipped += older.skipped + 1
        self.first_skipped_revision = older.first_skipped_revision or older.revision
        return self

    # Getters made by attrgetter, which are C: a callback reads these at every event, and a Python getter is a
    # function call each time (docs/performance-m8.md, "Claims and leases in C").
    operation = property(attrgetter("_ev.operation"), doc="ADD, OVERWRITE or DELETE.")
    revision = property(attrgetter("_ev.revision"), doc="The WM revision of the change.")
    type = property(attrgetter("_ev.type"), doc="Full message name of the entry's value.")
    version = property(attrgetter("_ev.version"), doc="The entry's version after the change.")
    source_component = property(attrgetter("_ev.source_component"), doc="Id of the writing component.")
    source_subarchitecture = property(attrgetter("_ev.source_subarchitecture"), doc="SA of the writer.")
    time_ns = property(attrgetter("_ev.time_ns"), doc="Server time of the change (ns since the epoch).")

    @property
    def address(self) -> WorkingMemoryAddress:
        """The entry changed."""
        return WorkingMemoryAddress(self._ev.id, self._ev.subarchitecture)

    id = property(attrgetter("_ev.id"), doc="The changed entry's id.")
    subarchitecture = property(attrgetter("_ev.subarchitecture"), doc="The SA whose WM changed.")

    @property
    def has_entry(self) -> bool:
        """Whether the event carries the entry (the filter set include_entry)."""
        return self._ev.entry is not None

    def entry(self, cls: builtins.type[M]) -> Entry[M]:
        """The entry carried by the event (after the write; for DELETE, as it was)."""
        if self._ev.entry is None:
            raise InvalidArgumentError("this change carries no entry: ask for it with include_entry=True")
        return entry_of(cls, self._ev.entry)

    def view(self) -> ValueView:
        """The value the event carries, not copied: shared memory on the server's host (:class:`cast.ValueView`)."""
        from cast.client.views import ValueView  # views builds on this module

        if self._ev.entry is None:
            raise InvalidArgumentError("this change carries no entry: ask for it with include_entry=True")
        return ValueView(self._ev.entry)

    def __repr__(self) -> str:
        return (
            f"WorkingMemoryChange({self.operation.name} {self.subarchitecture}/{self.id} "
            f"type={self.type} v={self.version} rev={self.revision} by={self.source_component})"
        )


class Task:
    """A task proposed by a managed component, as its task manager decided."""

    __slots__ = ("_rec",)

    def __init__(self, record: TaskRecord) -> None:
        self._rec = record

    task_id = property(attrgetter("_rec.task_id"), doc="Id given by the task manager.")
    name = property(attrgetter("_rec.name"), doc="Name given at proposal.")
    subarchitecture = property(attrgetter("_rec.subarchitecture"), doc="SA whose TM decided.")
    component = property(attrgetter("_rec.component"), doc="The proposer.")
    priority = property(attrgetter("_rec.priority"), doc="Priority given at proposal.")
    state = property(attrgetter("_rec.state"), doc="WAITING, ADOPTED, REJECTED, ...")
    reason = property(attrgetter("_rec.reason"), doc="Why it was rejected or ended.")

    def data(self, cls: type[M]) -> M | None:
        """The proposal's payload as ``cls`` (None if none was given)."""
        if not self._rec.data_type:
            return None
        what = f"task '{self.task_id}' data in subarchitecture '{self.subarchitecture}'"  # as C++ and Java say it
        return decode(cls, self._rec.data_type, self._rec.data, what)

    def __repr__(self) -> str:
        return f"Task({self.task_id} '{self.name}' {self.state.name})"


