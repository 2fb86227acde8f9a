"""Comparing two registrations of one .proto file by meaning, not by bytes.

Protobuf runtimes describe the same file differently: protoc fills in every
field's ``json_name`` and keeps the file's options (``java_package``, ...),
protobufjs drops options, source info and comments are optional. None of that
changes how a value's bytes parse, so none of it may make two registrations
disagree. What does change it is compared: the package and syntax, and for
every message (nested ones too) its fields (number, name, type, label and
presence, type name, oneof), its oneofs, and every enum's values; and the
file's extensions.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from google.protobuf import descriptor_pb2

__all__ = ["first_difference"]

FieldProto = descriptor_pb2.FieldDescriptorProto


def first_difference(old: descriptor_pb2.FileDescriptorProto, new: descriptor_pb2.FileDescriptorProto) -> str | None:
    """None if both define the same types; else the first difference, naming both definitions."""
    if old.package != new.package:
        return f"package is '{old.package}' in the registered file, '{new.package}' in this one"
    if (old.syntax or "proto2") != (new.syntax or "proto2"):
        return f"syntax is {old.syntax or 'proto2'} in the registered file, {new.syntax or 'proto2'} in this one"
    prefix = f"{old.package}." if old.package else ""
    return (
        _messages(prefix, old.message_type, new.message_type)
        or _enums(prefix, old.enum_type, new.enum_type)
        or _fields(prefix + "<extension>", old.extension, new.extension, ())
    )


def _by_name(items: Iterable[object]) -> dict[str, object]:
    return {item.name: item for item in items}  # type: ignore[attr-defined]


def _presence(what: str, scope: str, old_names: Iterable[str], new_names: Iterable[str]) -> str | None:
    old_set, new_set = set(old_names), set(new_names)
    if old_set - new_set:
        return f"{what} {scope}{sorted(old_set - new_set)[0]} is registered but missing from this file"
    if new_set - old_set:
        return f"{what} {scope}{sorted(new_set - old_set)[0]} is in this file but not in the registered one"
    return None


def _messages(
    scope: str, old: Sequence[descriptor_pb2.DescriptorProto], new: Sequence[descriptor_pb2.DescriptorProto]
) -> str | None:
    old_by, new_by = _by_name(old), _by_name(new)
    missing = _presence("message", scope, old_by, new_by)
    if missing:
        return missing
    for name in sorted(old_by):
        a, b = old_by[name], new_by[name]
        assert isinstance(a, descriptor_pb2.DescriptorProto) and isinstance(b, descriptor_pb2.DescriptorProto)
        full = scope + name
        oneofs_a = [o.name for o in a.oneof_decl]
        oneofs_b = [o.name for o in b.oneof_decl]
        if oneofs_a != oneofs_b:
            return f"message {full}: oneofs are {oneofs_a} in the registered file, {oneofs_b} in this one"
        diff = (
            _fields(full, a.field, b.field, oneofs_a)
            or _fields(full, a.extension, b.extension, oneofs_a)
            or _messages(full + ".", a.nested_type, b.nested_type)
            or _enums(full + ".", a.enum_type, b.enum_type)
        )
        if diff:
            return diff
    return None


def _fields(scope: str, old: Sequence[FieldProto], new: Sequence[FieldProto], oneofs: Sequence[str]) -> str | None:
    old_by = {f.number: f for f in old}
    new_by = {f.number: f for f in new}
    for number in sorted(set(old_by) | set(new_by)):
        a, b = old_by.get(number), new_by.get(number)
        if a is None or b is None:
            where = "this file" if a is None else "the registered file"
            present = b if a is None else a
            assert present is not None
            return f"{scope}: field {number} ({_show(present, oneofs)}) is only in {where}"
        if _meaning(a, oneofs) != _meaning(b, oneofs):
            return (
                f"{scope}: field {number} is '{_show(a, oneofs)}' in the registered file, "
                f"'{_show(b, oneofs)}' in this one"
            )
    return None


def _meaning(f: FieldProto, oneofs: Sequence[str]) -> tuple[object, ...]:
    oneof = oneofs[f.oneof_index] if f.HasField("oneof_index") and f.oneof_index < len(oneofs) else ""
    return (f.name, f.type, f.label, f.type_name.lstrip("."), oneof, f.proto3_optional, f.extendee.lstrip("."))


def _show(f: FieldProto, oneofs: Sequence[str]) -> str:
    label = FieldProto.Label.Name(f.label).removeprefix("LABEL_").lower()
    kind = f.type_name.lstrip(".") or FieldProto.Type.Name(f.type).removeprefix("TYPE_").lower()
    oneof = oneofs[f.oneof_index] if f.HasField("oneof_index") and f.oneof_index < len(oneofs) else ""
    extra = " (proto3 optional)" if f.proto3_optional else f" in oneof {oneof}" if oneof else ""
    return f"{label} {kind} {f.name} = {f.number}{extra}"


def _enums(
    scope: str, old: Sequence[descriptor_pb2.EnumDescriptorProto], new: Sequence[descriptor_pb2.EnumDescriptorProto]
) -> str | None:
    old_by, new_by = _by_name(old), _by_name(new)
    missing = _presence("enum", scope, old_by, new_by)
    if missing:
        return missing
    for name in sorted(old_by):
        a, b = old_by[name], new_by[name]
        assert isinstance(a, descriptor_pb2.EnumDescriptorProto) and isinstance(b, descriptor_pb2.EnumDescriptorProto)
        values_a = sorted((v.number, v.name) for v in a.value)
        values_b = sorted((v.number, v.name) for v in b.value)
        if values_a != values_b:
            changed = sorted(set(values_a) ^ set(values_b))[0]
            return (
                f"enum {scope}{name}: value {changed[1]} = {changed[0]} is only in "
                f"{'the registered file' if changed in values_a else 'this file'}"
            )
    return None
