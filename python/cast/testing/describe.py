"""Words for what a test saw: values, entries and changes, one line each, for failure messages.

A value is shown as its type and its fields in protobuf's text format on one line
(``google.protobuf.Int64Value {value: 3}``). A change carries its value's bytes
and type name only; it is shown decoded when the type's message class is loaded
in this process (the test imported it), and by its size otherwise.
"""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pool, message_factory, text_format
from google.protobuf.message import DecodeError, Message

from cast.client.types import Entry, WorkingMemoryChange

__all__ = ["describe_change", "describe_entry", "describe_value"]

MAX_VALUE_CHARS = 300
"""A longer value is cut, so that one large image does not bury the rest of a failure message."""


def _cut(text: str) -> str:
    return text if len(text) <= MAX_VALUE_CHARS else f"{text[:MAX_VALUE_CHARS]}... ({len(text)} characters)"


def describe_value(value: Message) -> str:
    """``Type {fields}`` on one line."""
    body = text_format.MessageToString(value, as_one_line=True)
    return _cut(f"{value.DESCRIPTOR.full_name} {{{body}}}")


def describe_bytes(type_name: str, data: bytes | memoryview) -> str:
    """A stored value given by its type name and bytes: decoded if its class is loaded here."""
    try:
        descriptor = descriptor_pool.Default().FindMessageTypeByName(type_name)
    except KeyError:
        return f"{type_name} ({len(data)} bytes)"
    try:
        value = message_factory.GetMessageClass(descriptor).FromString(bytes(data))
    except DecodeError:
        return f"{type_name} ({len(data)} bytes that do not parse)"
    return describe_value(value)


def describe_entry(entry: Entry[Any]) -> str:
    """An entry with its version and author."""
    return f"{describe_value(entry.value)} (version {entry.version}, by {entry.author})"


def describe_change(change: WorkingMemoryChange) -> str:
    """``ADD vision/count by counter (revision 3): value`` (the value when the change carries it)."""
    head = f"{change.operation.name} {change.subarchitecture}/{change.id} by {change.source_component} " \
           f"(revision {change.revision})"
    entry = change._ev.entry  # the record itself: its class may not be loaded here
    if entry is None:
        return f"{head}: {change.type}"
    return f"{head}: {describe_bytes(entry.type, entry.data)}"
