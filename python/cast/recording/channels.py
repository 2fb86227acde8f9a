"""From working-memory changes to channels and messages: the mapping every recording sink shares.

A sink (the MCAP file of ``cast record``, a live viewer) shows a system as
*channels* of protobuf messages, each with its schema, in the terms MCAP and
the Foxglove WebSocket protocol both use (topic, message encoding, schema name,
schema encoding, schema data, channel metadata). This module decides what
those channels are and what each change becomes; it writes nothing itself, so
every sink maps a working memory the same way (docs/recording.md, "The file"):

- ``/<SA>/<type>`` (role ``value``): the values of one entry type in one SA,
  each message the entry's bytes as written, its schema the
  ``FileDescriptorSet`` the writer registered (``Directory.GetSchema``), so a
  viewer decodes it with no CAST code. Deletes have no value.
- ``/cast/changes`` (role ``changes``): one ``cast.v1.ChangeEvent`` per change
  (operation, SA, id, type, version, revision, writer, commit time; the entry's
  author and revision in ``entry``, without its value). A change and its value
  carry the same ``sequence``, so a reader pairs them without relying on order.
- ``/cast/gaps`` (role ``gaps``): a ``google.protobuf.Struct`` per stretch of
  history the recorder could not get (see :class:`Gap`).

Channels are told apart by their metadata (``cast.role``, and for values
``cast.subarchitecture`` and ``cast.type``), never by parsing topics.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from google.protobuf import struct_pb2
from mcap_protobuf.schema import build_file_descriptor_set

from cast.core.records import ChangeEvent, Operation
from cast.v1 import entry_pb2

__all__ = [
    "CHANGES_TOPIC",
    "ENCODING",
    "FORMAT_VERSION",
    "GAPS_TOPIC",
    "MAX_SEQUENCE",
    "ROLE_CHANGES",
    "ROLE_GAPS",
    "ROLE_KEY",
    "ROLE_VALUE",
    "SA_KEY",
    "SCHEMA_KEY",
    "TYPE_KEY",
    "Change",
    "ChannelMap",
    "ChannelMessage",
    "ChannelSpec",
    "Gap",
    "SchemaSource",
    "change_record",
    "changes_channel",
    "gap_record",
    "gaps_channel",
    "parse_change",
    "parse_gap",
    "value_channel",
    "value_topic",
]

ENCODING = "protobuf"
"""Message and schema encoding of every channel (MCAP's and Foxglove's well-known name)."""

FORMAT_VERSION = "1"
"""Version of this mapping, recorded in each file's ``cast.recording`` metadata."""

CHANGES_TOPIC = "/cast/changes"
GAPS_TOPIC = "/cast/gaps"

ROLE_KEY = "cast.role"
SA_KEY = "cast.subarchitecture"
TYPE_KEY = "cast.type"
SCHEMA_KEY = "cast.schema"
ROLE_VALUE = "value"
ROLE_CHANGES = "changes"
ROLE_GAPS = "gaps"

MAX_SEQUENCE = 2**32 - 1
"""The largest sequence number (MCAP's ``sequence`` is a uint32): the most changes one file numbers."""


def value_topic(subarchitecture: str, type_name: str) -> str:
    """The topic of one entry type's values in one SA: ``/<SA>/<type>``.

    SA names have no ``/`` (letters, digits, ``_``, ``-``, ``.``), so the topic
    names exactly one pair.
    """
    return f"/{subarchitecture}/{type_name}"


@dataclass(frozen=True)
class ChannelSpec:
    """One channel as a sink announces it: topic, schema, metadata.

    ``schema_data`` is a serialized ``FileDescriptorSet`` holding the message's
    file and every file it imports; empty when no schema is known (a type that
    no writer registered), in which case ``schema_encoding`` is empty too.
    """

    topic: str
    role: str
    schema_name: str
    schema_data: bytes
    subarchitecture: str = ""
    type: str = ""

    @property
    def message_encoding(self) -> str:
        """How messages on the channel are encoded: always ``protobuf``."""
        return ENCODING

    @property
    def schema_encoding(self) -> str:
        """``protobuf``, or empty when the channel has no schema."""
        return ENCODING if self.schema_data else ""

    @property
    def key(self) -> tuple[str, str, str]:
        """What makes the channel unique: role, SA and type (a sink's dictionary key)."""
        return (self.role, self.subarchitecture, self.type)

    @property
    def metadata(self) -> dict[str, str]:
        """The channel's metadata: its role, and for values its SA, type and whether a schema was found."""
        out = {ROLE_KEY: self.role}
        if self.role == ROLE_VALUE:
            out[SA_KEY] = self.subarchitecture
            out[TYPE_KEY] = self.type
            out[SCHEMA_KEY] = "registered" if self.schema_data else "unregistered"
        return out


@dataclass(frozen=True)
class ChannelMessage:
    """One message for one channel; ``log_time`` in nanoseconds since the Unix epoch."""

    channel: ChannelSpec
    log_time: int
    sequence: int
    data: bytes


def value_channel(subarchitecture: str, type_name: str, schema: bytes) -> ChannelSpec:
    """The channel of one type's values in one SA, with the schema its writers registered (may be empty)."""
    return ChannelSpec(value_topic(subarchitecture, type_name), ROLE_VALUE, type_name, schema, subarchitecture,
                       type_name)


def _own_schema(message: type[entry_pb2.ChangeEvent] | type[struct_pb2.Struct]) -> bytes:
    return bytes(build_file_descriptor_set(message).SerializeToString())


_CHANGES = ChannelSpec(CHANGES_TOPIC, ROLE_CHANGES, entry_pb2.ChangeEvent.DESCRIPTOR.full_name,
                       _own_schema(entry_pb2.ChangeEvent))
_GAPS = ChannelSpec(GAPS_TOPIC, ROLE_GAPS, struct_pb2.Struct.DESCRIPTOR.full_name, _own_schema(struct_pb2.Struct))


def changes_channel() -> ChannelSpec:
    """The channel of change records (``cast.v1.ChangeEvent``)."""
    return _CHANGES


def gaps_channel() -> ChannelSpec:
    """The channel of gap markers (``google.protobuf.Struct``)."""
    return _GAPS


# ------------------------------------------------------------------- changes

@dataclass(frozen=True)
class Change:
    """A recorded change, as read back from its change record.

    ``author`` is the component that made this change (for a delete, the one
    that deleted); ``has_value`` says whether a value message with the same
    ``sequence`` belongs to it (never for a delete; not when the server withheld
    the value because another component held the entry ODR-locked).
    """

    sequence: int
    subarchitecture: str
    id: str
    type: str
    operation: Operation
    version: int
    revision: int
    author: str
    author_subarchitecture: str
    time_ns: int
    has_value: bool


def change_record(event: ChangeEvent) -> entry_pb2.ChangeEvent:
    """The change record of an event: everything but the value, which travels on the value channel."""
    pb = entry_pb2.ChangeEvent(
        revision=event.revision,
        operation=int(event.operation),  # type: ignore[arg-type]
        address=entry_pb2.EntryAddress(id=event.id, subarchitecture=event.subarchitecture),
        type=event.type,
        source_component=event.source_component,
        source_subarchitecture=event.source_subarchitecture,
        version=event.version,
    )
    pb.time.FromNanoseconds(event.time_ns)
    entry = event.entry
    if entry is not None:
        pb.entry.address.CopyFrom(pb.address)
        pb.entry.type = entry.type
        pb.entry.version = entry.version
        pb.entry.author = entry.author
        pb.entry.revision = entry.revision
        pb.entry.modified.FromNanoseconds(entry.modified_ns)
    return pb


def parse_change(data: bytes, sequence: int) -> Change:
    """A :class:`Change` from the bytes of a change record; ``google.protobuf`` DecodeError if they are not one."""
    pb = entry_pb2.ChangeEvent.FromString(data)
    operation = Operation(pb.operation)
    return Change(
        sequence=sequence,
        subarchitecture=pb.address.subarchitecture,
        id=pb.address.id,
        type=pb.type,
        operation=operation,
        version=pb.version,
        revision=pb.revision,
        author=pb.source_component,
        author_subarchitecture=pb.source_subarchitecture,
        time_ns=pb.time.ToNanoseconds(),
        has_value=operation is not Operation.DELETE and pb.HasField("entry"),
    )


# ---------------------------------------------------------------------- gaps

@dataclass(frozen=True)
class Gap:
    """Changes of one SA that are not in the recording, and why.

    The recording has every change of ``subarchitecture`` up to
    ``last_revision`` and from ``resumed_revision`` on; those between are
    missing. When the two histories differ (the server restarted without its
    history) revisions were numbered again, and how many are missing is not
    known (:attr:`missing` is None).
    """

    subarchitecture: str
    last_revision: int
    resumed_revision: int
    reason: str
    time_ns: int
    history_before: str = ""
    history_after: str = ""

    @property
    def missing(self) -> int | None:
        """How many changes are missing; None when the history changed and nobody can tell."""
        if self.history_before != self.history_after:
            return None
        return max(0, self.resumed_revision - self.last_revision - 1)

    def describe(self) -> str:
        """One line for people: what is missing and why."""
        if self.missing is None:
            what = (f"changes after revision {self.last_revision} of history {self.history_before or '?'} and "
                    f"before revision {self.resumed_revision} of history {self.history_after or '?'}")
        else:
            what = f"revisions {self.last_revision + 1}..{self.resumed_revision - 1} ({self.missing} changes)"
        return f"gap in subarchitecture '{self.subarchitecture}': {what} are not recorded: {self.reason}"


def gap_record(gap: Gap) -> struct_pb2.Struct:
    """The gap marker message."""
    record = struct_pb2.Struct()
    record.update({
        "subarchitecture": gap.subarchitecture,
        "last_revision": gap.last_revision,
        "resumed_revision": gap.resumed_revision,
        "missing": gap.missing,
        "reason": gap.reason,
        "history_before": gap.history_before,
        "history_after": gap.history_after,
    })
    return record


def parse_gap(data: bytes, time_ns: int) -> Gap:
    """A :class:`Gap` from the bytes of a gap marker."""
    fields = struct_pb2.Struct.FromString(data)
    return Gap(
        subarchitecture=str(fields["subarchitecture"]),
        last_revision=int(fields.fields["last_revision"].number_value),
        resumed_revision=int(fields.fields["resumed_revision"].number_value),
        reason=str(fields["reason"]),
        time_ns=time_ns,
        history_before=str(fields["history_before"]),
        history_after=str(fields["history_after"]),
    )


# ----------------------------------------------------------------------- map

SchemaSource = Callable[[str, str], bytes | None]
"""Returns the serialized ``FileDescriptorSet`` of a type as registered on an SA's server, or None."""


@dataclass
class ChannelMap:
    """Turns change events into channel messages, fetching each type's schema once per SA.

    ``schema_of(sa, type)`` asks the server (``Directory.GetSchema``); its
    answer is kept, a missing schema too (the channel then has none, and
    :attr:`unregistered` lists it). Thread-safe: a live viewer may map events
    from several watch threads.
    """

    schema_of: SchemaSource
    channels: dict[tuple[str, str], ChannelSpec] = field(default_factory=dict)
    unregistered: list[tuple[str, str]] = field(default_factory=list)
    _mutex: threading.Lock = field(default_factory=threading.Lock)

    def channel(self, subarchitecture: str, type_name: str) -> ChannelSpec:
        """The value channel of a type in an SA (its schema fetched on first use)."""
        key = (subarchitecture, type_name)
        with self._mutex:
            found = self.channels.get(key)
        if found is not None:
            return found
        schema = self.schema_of(subarchitecture, type_name)
        spec = value_channel(subarchitecture, type_name, schema or b"")
        with self._mutex:
            if key not in self.channels:
                self.channels[key] = spec
                if not schema:
                    self.unregistered.append(key)
            return self.channels[key]

    def messages(self, event: ChangeEvent, sequence: int) -> list[ChannelMessage]:
        """What one change becomes: its value (unless a delete, or withheld) and its change record."""
        out: list[ChannelMessage] = []
        entry = event.entry
        if entry is not None and event.operation is not Operation.DELETE:
            # A copy: the message outlives the event, and a value lent by shared memory is only lent while it lives.
            data = entry.data if isinstance(entry.data, bytes) else bytes(entry.data)
            out.append(ChannelMessage(self.channel(event.subarchitecture, event.type), event.time_ns, sequence, data))
        out.append(ChannelMessage(_CHANGES, event.time_ns, sequence, change_record(event).SerializeToString()))
        return out

    @staticmethod
    def gap_message(gap: Gap) -> ChannelMessage:
        """The marker of a gap, logged at the time the recorder learned of it."""
        return ChannelMessage(_GAPS, gap.time_ns, 0, gap_record(gap).SerializeToString())

