"""ROS 2 message types read from rclpy's generated classes at run time (no build step).

Every class rosidl generates for Python describes its fields:
``SLOT_TYPES`` holds a ``rosidl_parser.definition`` type per field, in the
order of ``get_fields_and_field_types()``; the class's metaclass holds its
constants. A team's own message package works as soon as it is on the ROS
path (its ``setup.bash`` sourced), as for any rclpy node.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from pathlib import Path
from typing import Any

from cast.bridges.ros.model import MESSAGE_KIND, Constant, Field, FieldType, MessageType, RosTypeError, split_ros_name

__all__ = ["describe", "message_class"]

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
    package, type_name = split_ros_name(name, 2)
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError as exc:
        raise RosTypeError(f"ROS 2 type {name}: no Python package '{package}' with messages on this interpreter "
                           f"({exc}); source the setup.bash of the ROS installation or workspace that has it, "
                           f"or install its wheel") from None
    cls = getattr(module, type_name, None)
    if cls is None or not hasattr(cls, "SLOT_TYPES"):
        known = sorted(n for n in dir(module) if not n.startswith("_") and hasattr(getattr(module, n), "SLOT_TYPES"))
        raise RosTypeError(f"ROS 2 type {name}: package {package} has no message {type_name} "
                           f"(it has: {', '.join(known) or 'none'})")
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
