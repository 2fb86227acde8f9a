"""ROS 2 message types read from rclpy's generated classes at run time (no build step).

Every class rosidl generates for Python describes its fields:
``SLOT_TYPES`` holds a ``rosidl_parser.definition`` type per field, in the
order of ``get_fields_and_field_types()``; the class's metaclass holds its
constants. A team's own message package works as soon as it is on the ROS
path (its ``setup.bash`` sourced), as for any rclpy node.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

from cast.bridges.ros.model import (
    MESSAGE_KIND,
    Constant,
    Field,
    FieldType,
    MessageType,
    RosTypeError,
    load_message_class,
    split_ros_name,
)

__all__ = ["describe", "message_class", "node_class"]

# rosidl_parser's basic type names -> the model's kinds ("long double" has no protobuf type: refused).
_BASIC = {
    "boolean": "bool", "octet": "octet", "char": "char", "wchar": "wchar",
    "float": "float32", "double": "float64",
    "short": "int16", "unsigned short": "uint16", "long": "int32", "unsigned long": "uint32",
    "long long": "int64", "unsigned long long": "uint64",
    **{k: k for k in ("int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64")},
}


def message_class(name: str) -> Any:
    """The rclpy class of ``pkg/msg/Name``; RosTypeError saying what is missing."""
    return load_message_class(name, 2, "SLOT_TYPES", "install its wheel")


def node_class(name: str) -> Any:
    """The rclpy class of ``pkg/msg/Name`` with its type support loaded, as a publisher or subscription needs it.

    A package's Python half imports without its compiled half (the type support libraries, found on
    LD_LIBRARY_PATH), and rclpy would only say "Could not import 'rosidl_typesupport_c'" when the
    bridge subscribes: RosTypeError names the library that did not load and what puts it on the path.
    """
    from rosidl_generator_py.import_type_support_impl import UnsupportedTypeSupport

    cls = message_class(name)
    cause: BaseException | None = None
    try:
        cls.__import_type_support__()
    except (UnsupportedTypeSupport, ImportError) as exc:  # rosidl raises the first while handling an ImportError
        cause = exc.__context__ or exc
    if cause is not None or getattr(cls, "_TYPE_SUPPORT", None) is None:
        package = split_ros_name(name, 2)[0]
        raise RosTypeError(f"ROS 2 type {name}: the type support of package {package} does not load "
                           f"({cause or 'no type support imported'}); its libraries (lib/ of the install space that "
                           f"has it) must be on LD_LIBRARY_PATH, as sourcing its setup.bash puts them")
    return cls


def _nested_name(t: Any) -> str:
    namespaces = list(t.namespaces)
    return "/".join([*namespaces, t.name])


def _element(t: Any, where: str) -> FieldType:
    from rosidl_parser import definition as d

    if isinstance(t, d.BasicType):
        kind = _BASIC.get(t.typename)
        if kind is None:
            raise RosTypeError(f"{where}: the ROS type '{t.typename}' has no protobuf equivalent")
        return FieldType(kind)
    if isinstance(t, d.NamespacedType):
        if len(t.namespaces) != 2 or t.namespaces[1] != "msg":
            raise RosTypeError(f"{where}: nested type {_nested_name(t)} is not a message (only msg types map)")
        return FieldType(MESSAGE_KIND, message=_nested_name(t))
    if isinstance(t, d.BoundedString):
        return FieldType("string", string_bound=int(t.maximum_size))
    if isinstance(t, d.UnboundedString):
        return FieldType("string")
    if isinstance(t, d.BoundedWString):
        return FieldType("wstring", string_bound=int(t.maximum_size))
    if isinstance(t, d.UnboundedWString):
        return FieldType("wstring")
    raise RosTypeError(f"{where}: unsupported ROS type {type(t).__name__}")


def _field_type(t: Any, where: str) -> FieldType:
    from rosidl_parser import definition as d

    if isinstance(t, d.Array):
        e = _element(t.value_type, where)
        return FieldType(e.kind, e.message, "fixed", int(t.size), e.string_bound)
    if isinstance(t, d.BoundedSequence):
        e = _element(t.value_type, where)
        return FieldType(e.kind, e.message, "bounded", int(t.maximum_size), e.string_bound)
    if isinstance(t, d.UnboundedSequence):
        e = _element(t.value_type, where)
        return FieldType(e.kind, e.message, "unbounded", 0, e.string_bound)
    return _element(t, where)


_CONSTANT_LINE = re.compile(r"^\s*([A-Za-z0-9_/]+(?:<=\d+)?)\s+([A-Z][A-Z0-9_]*)\s*=")


def _msg_file(package: str, type_name: str) -> Path | None:
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [sys.prefix]
    for prefix in prefixes:
        path = Path(prefix) / "share" / package / "msg" / f"{type_name}.msg"
        if path.is_file():
            return path
    return None


def _constant_kinds(package: str, type_name: str) -> dict[str, str]:
    """The declared type of each constant, from the package's installed .msg file when there is one."""
    path = _msg_file(package, type_name)
    if path is None:
        return {}
    kinds: dict[str, str] = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        m = _CONSTANT_LINE.match(line)
        if m:
            kinds[m.group(2)] = m.group(1)
    return kinds


def _inferred_kind(value: object) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int64"
    if isinstance(value, float):
        return "float64"
    return "string"


def describe(name: str) -> MessageType:
    """The model of the ROS 2 type ``pkg/msg/Name``; RosTypeError if it cannot be had or mapped."""
    cls = message_class(name)
    package, type_name = split_ros_name(name, 2)
    names = list(cls.get_fields_and_field_types())
    slots = list(cls.SLOT_TYPES)
    fields = tuple(Field(n, _field_type(t, f"ROS 2 type {name}, field {n}")) for n, t in zip(names, slots, strict=True))
    meta = type(cls)
    values: dict[str, object] = dict(getattr(meta, f"_{meta.__name__}__constants", {}) or {})
    kinds = _constant_kinds(package, type_name) if values else {}
    constants = tuple(Constant(k, kinds.get(k, _inferred_kind(v)), v) for k, v in values.items())
    return MessageType(name, 2, fields, constants)
