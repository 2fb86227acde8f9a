"""Change filters and their helpers (docs/design.md section 5).

A :class:`ChangeFilter` says which change events a callback wants. "Local"
filters match the component's own subarchitecture; the SA is filled in when
the filter is registered with ``on_change``, so helpers need no component.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from google.protobuf.message import Message

from cast.core.records import Operation
from cast.core.watch import EventFilter

__all__ = [
    "ChangeFilter",
    "TypeLike",
    "address_filter",
    "global_type_filter",
    "local_type_filter",
    "operation_filter",
    "source_filter",
    "type_name",
]

TypeLike = type[Message] | str
"""A protobuf message class, or its full name."""

LOCAL = "\x00local"  # placeholder SA replaced by the component's own on registration


def type_name(t: TypeLike) -> str:
    """The full protobuf name of a message class (or the name itself)."""
    if isinstance(t, str):
        return t
    return str(t.DESCRIPTOR.full_name)


@dataclass(frozen=True)
class ChangeFilter(EventFilter):
    """Which events to deliver: the core's :class:`EventFilter`, whose SA may be "the component's own".

    Every set field must match; empty fields match anything. The fields are the
    core's, so a filter means the same in process and over the wire.
    """

    def resolve(self, own_subarchitecture: str) -> EventFilter:
        """The core filter, with a local SA placeholder replaced by ``own_subarchitecture``."""
        values = {f.name: getattr(self, f.name) for f in fields(EventFilter)}
        if self.subarchitecture == LOCAL:
            values["subarchitecture"] = own_subarchitecture
        return EventFilter(**values)

    def with_entry(self) -> ChangeFilter:
        """The same filter, asking for the entry in each event."""
        return replace(self, include_entry=True)


def _ops(ops: tuple[Operation, ...]) -> frozenset[Operation]:
    return frozenset(Operation(op) for op in ops)


def local_type_filter(t: TypeLike, *operations: Operation, include_entry: bool = False) -> ChangeFilter:
    """Changes to entries of type ``t`` in the component's own SA."""
    return ChangeFilter(_ops(operations), type_name(t), subarchitecture=LOCAL, include_entry=include_entry)


def global_type_filter(t: TypeLike, *operations: Operation, include_entry: bool = False) -> ChangeFilter:
    """Changes to entries of type ``t`` in every SA."""
    return ChangeFilter(_ops(operations), type_name(t), include_entry=include_entry)


def address_filter(
    entry_id: str, *operations: Operation, subarchitecture: str | None = None, include_entry: bool = False
) -> ChangeFilter:
    """Changes to one entry (in the own SA unless ``subarchitecture`` is given)."""
    return ChangeFilter(
        _ops(operations), id=entry_id, subarchitecture=subarchitecture or LOCAL, include_entry=include_entry
    )


def source_filter(
    component_id: str, *operations: Operation, subarchitecture: str = "", include_entry: bool = False
) -> ChangeFilter:
    """Changes made by one component (in every SA unless ``subarchitecture`` is given)."""
    return ChangeFilter(
        _ops(operations), source_component=component_id, subarchitecture=subarchitecture, include_entry=include_entry
    )


def operation_filter(*operations: Operation, local: bool = False, include_entry: bool = False) -> ChangeFilter:
    """Changes of the given operations (every SA, or only the own one if ``local``)."""
    return ChangeFilter(_ops(operations), subarchitecture=LOCAL if local else "", include_entry=include_entry)
