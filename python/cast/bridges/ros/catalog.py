"""The ROS types one bridge (or one ``cast ros-types``) knows: read once, with their protobuf classes.

A catalog belongs to one ROS generation and reads types through that
generation's introspection (``ros2_types`` or ``ros1_types``), each type once,
with every type it nests. Its protobuf classes live in a descriptor pool of
its own, filled as types are asked for.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message, message_factory

from cast.bridges.ros.descriptors import file_proto
from cast.bridges.ros.model import MessageType, RosTypeError, proto_name

__all__ = ["TypeCatalog"]


def _introspection(ros: int) -> tuple[Callable[[str], MessageType], Callable[[str], Any]]:
    if ros == 2:
        from cast.bridges.ros import ros2_types

        return ros2_types.describe, ros2_types.message_class
    if ros == 1:
        from cast.bridges.ros import ros1_types

        def ros1_class(name: str) -> Any:
            if name in ros1_types.BUILTIN_TYPES:
                import genpy

                return genpy.Time if name == "time" else genpy.Duration
            return ros1_types.message_class(name)

        return ros1_types.describe, ros1_class
    raise RosTypeError(f"ROS generation {ros}: the bridge speaks ROS 1 and ROS 2")


class TypeCatalog:
    """ROS message types of one generation, their protobuf descriptors and classes. Thread-safe."""

    def __init__(self, ros: int, describe: Callable[[str], MessageType] | None = None,
                 ros_class: Callable[[str], Any] | None = None) -> None:
        self.ros = ros
        if describe is None or ros_class is None:
            default_describe, default_class = _introspection(ros)
            describe = describe or default_describe
            ros_class = ros_class or default_class
        self._describe = describe
        self._ros_class = ros_class
        self._types: dict[str, MessageType] = {}
        self._classes: dict[str, type[message.Message]] = {}
        self._ros_classes: dict[str, Any] = {}
        self._pool = descriptor_pool.DescriptorPool()
        self._mutex = threading.RLock()

    def describe(self, name: str) -> MessageType:
        """The model of one type (read once); RosTypeError when it cannot be had."""
        with self._mutex:
            found = self._types.get(name)
            if found is None:
                found = self._types[name] = self._describe(name)
            return found

    def closure(self, names: Iterable[str]) -> list[MessageType]:
        """The named types and every type they nest, each once, nested types first."""
        out: list[MessageType] = []
        seen: set[str] = set()

        def visit(name: str, trail: tuple[str, ...]) -> None:
            if name in seen:
                return
            if name in trail:
                raise RosTypeError(f"ROS type {name} contains itself ({' -> '.join((*trail, name))})")
            t = self.describe(name)
            for dep in t.dependencies():
                visit(dep, (*trail, name))
            seen.add(name)
            out.append(t)

        for name in names:
            visit(name, ())
        return out

    def files(self, names: Iterable[str]) -> list[descriptor_pb2.FileDescriptorProto]:
        """The ``.proto`` files (as descriptors) of the named types and those they nest, dependencies first."""
        return [file_proto(t) for t in self.closure(names)]

    def proto_class(self, name: str) -> type[message.Message]:
        """The protobuf class of a ROS type (``ros2.sensor_msgs.msg.Image`` for ``sensor_msgs/msg/Image``)."""
        with self._mutex:
            found = self._classes.get(name)
            if found is not None:
                return found
            for t in self.closure([name]):
                if t.name not in self._classes:
                    self._pool.Add(file_proto(t))
                    self._classes[t.name] = message_factory.GetMessageClass(
                        self._pool.FindMessageTypeByName(proto_name(t.name, t.ros)))
            return self._classes[name]

    def ros_class(self, name: str) -> Any:
        """The ROS client library's class of a type."""
        with self._mutex:
            found = self._ros_classes.get(name)
            if found is None:
                found = self._ros_classes[name] = self._ros_class(name)
            return found
