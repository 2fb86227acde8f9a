"""What ``cast ros-types`` does: ROS message types to ``.proto`` files (and a descriptor set), no build step.

Run it with the interpreter that has the ROS messages (the one the bridge runs
with): ``cast ros-types sensor_msgs/msg/Image -o protos/`` for ROS 2,
``cast ros-types --ros 1 sensor_msgs/Image -o protos/`` for ROS 1. A bare
package name (``sensor_msgs``) stands for every message type of the package.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from google.protobuf import descriptor_pb2

from cast.bridges.ros.catalog import TypeCatalog
from cast.bridges.ros.model import MessageType, RosTypeError
from cast.bridges.ros.protofile import write_protos

__all__ = ["expand", "generate"]


def _package_types(package: str, ros: int) -> list[str]:
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError as exc:
        raise RosTypeError(f"ROS {ros} package {package}: no message module on this interpreter ({exc})") from None
    marker = "SLOT_TYPES" if ros == 2 else "_slot_types"
    names = sorted(n for n in dir(module) if not n.startswith("_") and hasattr(getattr(module, n), marker))
    if not names:
        raise RosTypeError(f"ROS {ros} package {package} has no message types")
    return [f"{package}/msg/{n}" if ros == 2 else f"{package}/{n}" for n in names]


def expand(names: list[str], ros: int) -> list[str]:
    """The type names given, a bare package name replaced by every message type of the package."""
    out: list[str] = []
    for name in names:
        out.extend(_package_types(name, ros) if "/" not in name and name not in ("time", "duration") else [name])
    return out


def generate(names: list[str], ros: int, out_dir: Path | None = None,
             descriptor_set: Path | None = None) -> list[MessageType]:
    """Write the ``.proto`` files of the types and all they nest under ``out_dir``; the types written.

    ``descriptor_set``: also write them as a ``FileDescriptorSet`` (the
    descriptors the bridge registers), for ``protoc --descriptor_set_in`` or a tool.
    """
    catalog = TypeCatalog(ros)
    types = catalog.closure(expand(names, ros))
    if out_dir is not None:
        write_protos(types, out_dir)
    if descriptor_set is not None:
        fds = descriptor_pb2.FileDescriptorSet(file=catalog.files(t.name for t in types))
        descriptor_set.parent.mkdir(parents=True, exist_ok=True)
        descriptor_set.write_bytes(fds.SerializeToString())
    return types
