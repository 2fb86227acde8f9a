"""A ROS message type as the bridge sees it, and the name of the protobuf entry type it becomes.

Both ROS generations are read into this one model (``ros2_types`` from
rclpy's classes, ``ros1_types`` from rospy's), so the descriptors, the
``.proto`` text and the conversion are written once.

The naming scheme (docs/ros.md, "Entry types"):

- ROS 2 ``pkg/msg/Name`` is the protobuf message ``ros2.pkg.msg.Name``, in
  the file ``ros2/pkg/msg/name.proto`` (the name in lower case with
  underscores, as rosidl names its own files).
- ROS 1 ``pkg/Name`` is ``ros1.pkg.msg.Name`` in ``ros1/pkg/msg/name.proto``;
  its built-in ``time`` and ``duration`` are ``ros1.builtin.Time`` and
  ``ros1.builtin.Duration`` (``ros1/builtin/time.proto``, ``duration.proto``).

The generation is part of the name because the two define the same names
differently (a ROS 1 ``Header`` has ``seq`` and a ``time``; a ROS 2 one has
``builtin_interfaces/Time``), and the server keeps one schema per name.
"""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "BYTES_KINDS",
    "FLOAT_KINDS",
    "INT_RANGES",
    "Constant",
    "Field",
    "FieldType",
    "MessageType",
    "RosTypeError",
    "proto_file",
    "proto_name",
    "proto_package",
    "ros_name_of_proto",
    "snake_case",
    "split_ros_name",
]


class RosTypeError(ValueError):
    """A ROS type name that is malformed or names no message type this ROS installation has."""


# Integer kinds and the values each holds; the bridge refuses anything outside on the way to ROS.
INT_RANGES: dict[str, tuple[int, int]] = {
    "int8": (-(1 << 7), (1 << 7) - 1),
    "int16": (-(1 << 15), (1 << 15) - 1),
    "int32": (-(1 << 31), (1 << 31) - 1),
    "int64": (-(1 << 63), (1 << 63) - 1),
    "uint8": (0, (1 << 8) - 1),
    "uint16": (0, (1 << 16) - 1),
    "uint32": (0, (1 << 32) - 1),
    "uint64": (0, (1 << 64) - 1),
    "octet": (0, 255),  # ROS 2 byte
    "char": (0, 255),  # ROS 2 IDL char (a str of one character in rclpy)
    "wchar": (0, 0xFFFF),
}
FLOAT_KINDS = ("float32", "float64")
# Element kinds whose arrays become one protobuf `bytes` field.
BYTES_KINDS = ("uint8", "octet")
SCALAR_KINDS = ("bool", *INT_RANGES, *FLOAT_KINDS, "string", "wstring")
# A nested message, or ROS 1's built-in time and duration (each a small message of its own).
MESSAGE_KIND = "message"


@dataclass(frozen=True)
class FieldType:
    """The type of one field.

    ``kind`` is a scalar kind (``SCALAR_KINDS``) or ``message`` with
    ``message`` naming the nested ROS type. ``array`` is ``""`` (one value),
    ``fixed`` (exactly ``size`` values), ``bounded`` (at most ``size``) or
    ``unbounded``. ``string_bound`` is the most characters of a bounded
    string (0: unbounded).
    """

    kind: str
    message: str = ""
    array: str = ""
    size: int = 0
    string_bound: int = 0

    @property
    def is_bytes(self) -> bool:
        """Whether the field is an array of bytes, carried as one protobuf ``bytes`` value."""
        return bool(self.array) and self.kind in BYTES_KINDS

    def ros_text(self) -> str:
        """The type as a ROS .msg file writes it (``float64[9]``, ``string<=8``, ``std_msgs/Header[]``)."""
        base = self.message if self.kind == MESSAGE_KIND else ("byte" if self.kind == "octet" else self.kind)
        if self.string_bound:
            base += f"<={self.string_bound}"
        if self.array == "fixed":
            return f"{base}[{self.size}]"
        if self.array == "bounded":
            return f"{base}[<={self.size}]"
        if self.array == "unbounded":
            return f"{base}[]"
        return base


@dataclass(frozen=True)
class Field:
    """One field of a message: its name and type."""

    name: str
    type: FieldType


@dataclass(frozen=True)
class Constant:
    """A constant a message type declares (``uint8 POWER_SUPPLY_STATUS_FULL = 4``)."""

    name: str
    kind: str
    value: object


@dataclass(frozen=True)
class MessageType:
    """A ROS message type: its name (``sensor_msgs/msg/Image`` or ``sensor_msgs/Image``), generation, fields."""

    name: str
    ros: int
    fields: tuple[Field, ...]
    constants: tuple[Constant, ...] = ()
    nested: tuple[str, ...] = field(default=(), compare=False)

    @property
    def proto_name(self) -> str:
        """The full protobuf name of the entry type it becomes."""
        return proto_name(self.name, self.ros)

    def dependencies(self) -> list[str]:
        """The ROS names of the message types its fields use, each once, in field order."""
        out: list[str] = []
        for f in self.fields:
            if f.type.kind == MESSAGE_KIND and f.type.message not in out:
                out.append(f.type.message)
        return out


_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
ROS1_BUILTINS = {"time": "Time", "duration": "Duration"}


def split_ros_name(name: str, ros: int) -> tuple[str, str]:
    """``(package, Name)`` of a ROS type name; RosTypeError naming the form expected.

    ROS 2 names are ``pkg/msg/Name``; ROS 1 names are ``pkg/Name`` (and its
    built-ins ``time`` and ``duration``).
    """
    if ros == 1 and name in ROS1_BUILTINS:
        return "builtin", ROS1_BUILTINS[name]
    parts = name.split("/")
    if ros == 2:
        if len(parts) == 3 and parts[1] == "msg" and _NAME.fullmatch(parts[0]) and _NAME.fullmatch(parts[2]):
            return parts[0], parts[2]
        raise RosTypeError(f"'{name}' is not a ROS 2 message type name: write it as package/msg/Name "
                           f"(for example sensor_msgs/msg/Image)")
    if len(parts) == 2 and _NAME.fullmatch(parts[0]) and _NAME.fullmatch(parts[1]):
        return parts[0], parts[1]
    raise RosTypeError(f"'{name}' is not a ROS 1 message type name: write it as package/Name "
                       f"(for example sensor_msgs/Image)")


def proto_package(name: str, ros: int) -> str:
    """The protobuf package of a ROS type: ``ros2.pkg.msg``, ``ros1.pkg.msg``, or ``ros1.builtin``."""
    package, _ = split_ros_name(name, ros)
    if ros == 1 and name in ROS1_BUILTINS:
        return "ros1.builtin"
    return f"ros{ros}.{package}.msg"


def proto_name(name: str, ros: int) -> str:
    """The full protobuf message name of a ROS type (``ros2.sensor_msgs.msg.Image``)."""
    return f"{proto_package(name, ros)}.{split_ros_name(name, ros)[1]}"


def snake_case(name: str) -> str:
    """``PoseWithCovarianceStamped`` -> ``pose_with_covariance_stamped``, as rosidl names its files."""
    out = re.sub(r"(.)([A-Z][a-z]+)", r"\1_\2", name)
    return re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", out).lower()


def proto_file(name: str, ros: int) -> str:
    """The path of the ``.proto`` file defining a ROS type (``ros2/sensor_msgs/msg/image.proto``)."""
    return proto_package(name, ros).replace(".", "/") + f"/{snake_case(split_ros_name(name, ros)[1])}.proto"


def ros_name_of_proto(full_name: str) -> tuple[str, int] | None:
    """The ROS type name and generation of a protobuf name this scheme made, else None."""
    parts = full_name.split(".")
    if full_name in ("ros1.builtin.Time", "ros1.builtin.Duration"):
        return parts[-1].lower(), 1
    if len(parts) == 4 and parts[0] in ("ros1", "ros2") and parts[2] == "msg":
        ros = int(parts[0][3])
        return (f"{parts[1]}/msg/{parts[3]}" if ros == 2 else f"{parts[1]}/{parts[3]}"), ros
    return None


def load_message_class(name: str, ros: int, slots: str, install: str) -> Any:
    """The ROS ``ros`` class of message ``name``, known by its ``slots`` attribute; RosTypeError saying what is missing.

    ``install``: how to get a missing package (the end of the error's advice).
    """
    package, type_name = split_ros_name(name, ros)
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError as exc:
        raise RosTypeError(f"ROS {ros} type {name}: no Python package '{package}' with messages on this interpreter "
                           f"({exc}); source the setup.bash of the ROS installation or workspace that has it, "
                           f"or {install}") from None
    cls = getattr(module, type_name, None)
    if cls is None or not hasattr(cls, slots):
        known = sorted(n for n in dir(module) if not n.startswith("_") and hasattr(getattr(module, n), slots))
        raise RosTypeError(f"ROS {ros} type {name}: package {package} has no message {type_name} "
                           f"(it has: {', '.join(known) or 'none'})")
    return cls
