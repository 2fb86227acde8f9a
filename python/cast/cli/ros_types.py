"""``cast ros-types TYPE... -o DIR``: ROS message types as .proto files for C++, Java and Python builds (docs/ros.md).

Run it with the interpreter that has the ROS messages (``rclpy`` for ROS 2,
``rospy`` for ROS 1 with ``--ros 1``): the types are read from the ROS client
library's message classes, as the bridge reads them.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cast.bridges.ros.generate import generate
from cast.bridges.ros.model import RosTypeError
from cast.errors import InvalidArgumentError

__all__ = ["add_commands"]


def _ros_types(args: argparse.Namespace) -> int:
    if args.out is None and args.descriptor_set is None:
        raise InvalidArgumentError("say where to write: -o DIR for .proto files, --descriptor-set FILE, or both")
    try:
        types = generate(args.types, args.ros, Path(args.out) if args.out else None,
                         Path(args.descriptor_set) if args.descriptor_set else None)
    except RosTypeError as exc:
        raise InvalidArgumentError(str(exc)) from None
    if not args.quiet:
        for t in types:
            print(f"{t.name} -> {t.proto_name}")
    return 0


def add_commands(sub: Any) -> None:
    """Add ``cast ros-types``."""
    p = sub.add_parser("ros-types", help="write ROS message types as .proto files (the entry types the ROS "
                                         "bridge writes: docs/ros.md)")
    p.add_argument("types", nargs="+", metavar="TYPE",
                   help="ROS message types (sensor_msgs/msg/Image; ROS 1: sensor_msgs/Image), or a package name "
                        "for all its messages; the types they nest are written too")
    p.add_argument("-o", "--out", metavar="DIR", help="write one .proto file per type under DIR "
                                                      "(ros2/sensor_msgs/msg/image.proto)")
    p.add_argument("--descriptor-set", metavar="FILE", help="also write the types as a FileDescriptorSet")
    p.add_argument("--ros", type=int, choices=(1, 2), default=2, help="ROS generation (default 2: rclpy)")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing")
    p.set_defaults(fn=_ros_types)
