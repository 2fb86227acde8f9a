"""ROS 1 message types read from rospy's (genpy's) generated classes at run time (no build step).

A genpy class lists its fields in ``__slots__`` and their types in
``_slot_types`` (``float64[9]``, ``uint8[]``, ``std_msgs/Header``, ``time``);
its ``_full_text`` is the definition, whose constants genmsg parses. ROS 1's
``char`` is an alias of ``uint8`` and its ``byte`` of ``int8``; ``time`` and
``duration`` are built-ins, modelled as small messages of their own.
"""

from __future__ import annotations

import re
from typing import Any

from cast.bridges.ros.model import (
    MESSAGE_KIND,
    ROS1_BUILTINS,
    Constant,
    Field,
    FieldType,
    MessageType,
    RosTypeError,
    load_message_class,
    split_ros_name,
)

__all__ = ["BUILTIN_TYPES", "describe", "message_class"]

_ALIASES = {"char": "uint8", "byte": "int8"}
_PRIMITIVES = ("bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64",
               "float32", "float64", "string")
_ARRAY = re.compile(r"^(?P<base>[^\[]+)(?:\[(?P<size>\d*)\])?$")

# ROS 1 time is two unsigned 32-bit counts; a duration two signed ones (genpy.Time, genpy.Duration).
BUILTIN_TYPES = {
    "time": MessageType("time", 1, (Field("secs", FieldType("uint32")), Field("nsecs", FieldType("uint32")))),
    "duration": MessageType("duration", 1, (Field("secs", FieldType("int32")), Field("nsecs", FieldType("int32")))),
}


def message_class(name: str) -> Any:
    """The rospy class of ``pkg/Name``; RosTypeError saying what is missing."""
    package = name.partition("/")[0]
    return load_message_class(name, 1, "_slot_types",
                              f"install its Debian package (python3-{package.replace('_', '-')})")


def _field_type(text: str, package: str, where: str) -> FieldType:
    m = _ARRAY.match(text.strip())
    if m is None:
        raise RosTypeError(f"{where}: cannot read the type '{text}'")
    base, size = m.group("base"), m.group("size")
    base = _ALIASES.get(base, base)
    if size is None:
        array, count = "", 0
    elif size == "":
        array, count = "unbounded", 0
    else:
        array, count = "fixed", int(size)
    if base in _PRIMITIVES:
        return FieldType(base, array=array, size=count)
    if base in ROS1_BUILTINS:
        return FieldType(MESSAGE_KIND, message=base, array=array, size=count)
    if base == "Header":
        base = "std_msgs/Header"
    elif "/" not in base:
        base = f"{package}/{base}"
    return FieldType(MESSAGE_KIND, message=base, array=array, size=count)


def _constants(cls: Any, name: str) -> tuple[Constant, ...]:
    text = str(getattr(cls, "_full_text", ""))
    own = re.split(r"\n={10,}\n", text, maxsplit=1)[0]
    try:
        import genmsg
        from genmsg import msg_loader

        spec = msg_loader.load_msg_from_string(genmsg.MsgContext.create_default(), own, name)
    except Exception:  # noqa: BLE001 - constants are comments in the .proto: without genmsg there are none
        return ()
    return tuple(Constant(c.name, _ALIASES.get(c.type, c.type), c.val) for c in spec.constants)


def describe(name: str) -> MessageType:
    """The model of the ROS 1 type ``pkg/Name`` (or ``time``, ``duration``); RosTypeError if it cannot be had."""
    if name in BUILTIN_TYPES:
        return BUILTIN_TYPES[name]
    cls = message_class(name)
    package, _ = split_ros_name(name, 1)
    fields = tuple(Field(n, _field_type(t, package, f"ROS 1 type {name}, field {n}"))
                   for n, t in zip(cls.__slots__, cls._slot_types, strict=True))
    return MessageType(name, 1, fields, _constants(cls, name))
