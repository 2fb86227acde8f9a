"""Round trips of every message type of some ROS packages, with edge values (run by the ROS interpreter).

For each type and each of three variants of edge values (integer limits,
infinities, NaN, -0.0, subnormals, empty, long and full-bounded arrays,
non-ASCII strings) a protobuf message is filled, converted to the ROS message,
serialised and parsed by ROS itself (rclpy's or genpy's serialiser), converted
back, and compared byte for byte with the first. Misfits (a value out of its
ROS range, a fixed array of the wrong length, a bounded string or array too
long) must be refused with the field named. Prints one JSON object:
{"types": {name: error or null}, "misfits": {case: error text}}.

Usage: python roundtrip.py ROS_GENERATION PACKAGE...
"""

from __future__ import annotations

import json
import math
import struct
import sys
import traceback
from typing import Any

from cast.bridges.ros.catalog import TypeCatalog
from cast.bridges.ros.convert import ConversionError, Converter
from cast.bridges.ros.generate import expand
from cast.bridges.ros.model import INT_RANGES, MESSAGE_KIND, FieldType

FLOAT32_MAX = struct.unpack("<f", struct.pack("<I", 0x7F7FFFFF))[0]
FLOAT32_TINY = struct.unpack("<f", struct.pack("<I", 1))[0]
TEXTS = ["", "ünïcødé: 日本語, ελληνικά, emoji 🤖 and 'quotes' \"too\"", "x" * 3000]


def scalar(kind: str, variant: int, ros: int, index: int) -> Any:
    if kind == "bool":
        return variant == 1 or index % 2 == 1
    if kind in INT_RANGES:
        lo, hi = INT_RANGES[kind]
        if kind == "wchar":
            hi = 0xD7FF  # below the UTF-16 surrogates, which are no characters
        return [lo, hi, (lo + hi) // 2 + index][variant] if kind not in ("octet", "char") else [0, 255, 65][variant]
    if kind == "float32":
        return [-math.inf, FLOAT32_MAX, math.nan, -0.0, FLOAT32_TINY][(variant + index) % 5] if index else \
            [-math.inf, math.inf, math.nan][variant]
    if kind == "float64":
        return [-math.inf, sys.float_info.max, math.nan, -0.0, 5e-324][(variant + index) % 5] if index else \
            [-math.inf, math.inf, math.nan][variant]
    raise AssertionError(kind)


def text(t: FieldType, variant: int) -> str:
    s = TEXTS[variant]
    return s[: t.string_bound] if t.string_bound else s


def count(t: FieldType, variant: int, nested: bool) -> int:
    if t.array == "fixed":
        return t.size
    if t.array == "bounded":
        return [0, t.size, min(1, t.size)][variant]
    return [0, 3 if nested else 1000, 2][variant]


def fill(catalog: TypeCatalog, name: str, pb: Any, variant: int, depth: int = 0) -> None:
    t = catalog.describe(name)
    ros1_time = catalog.ros == 1 and name in ("time", "duration")
    for f in t.fields:
        ft = f.type
        if ros1_time:  # genpy normalises nsecs over 1e9 as it parses: a valid time is what ROS 1 carries
            setattr(pb, f.name, [0, 999_999_999, 123][variant] if f.name == "nsecs" else
                    scalar(ft.kind, variant, 1, 0))
            continue
        if ft.kind == MESSAGE_KIND:
            if ft.array:
                for _ in range(count(ft, variant, True) if depth < 2 else min(1, count(ft, variant, True))):
                    fill(catalog, ft.message, getattr(pb, f.name).add(), variant, depth + 1)
            else:
                fill(catalog, ft.message, getattr(pb, f.name), variant, depth + 1)
        elif ft.is_bytes:
            n = count(ft, variant, False)
            setattr(pb, f.name, bytes((i * 7 + variant) % 256 for i in range(n)) if variant != 1 else
                    b"\xff" * n)
        elif ft.kind in ("string", "wstring"):
            if ft.array:
                getattr(pb, f.name).extend(text(ft, (variant + i) % 3) for i in range(count(ft, variant, True)))
            else:
                setattr(pb, f.name, text(ft, variant))
        elif ft.array:
            n = count(ft, variant, False)
            getattr(pb, f.name).extend(scalar(ft.kind, variant, catalog.ros, i) for i in range(n))
        else:
            setattr(pb, f.name, scalar(ft.kind, variant, catalog.ros, 0))


def ros_wire_round_trip(catalog: TypeCatalog, name: str, msg: Any) -> Any:
    if catalog.ros == 2:
        from rclpy.serialization import deserialize_message, serialize_message

        return deserialize_message(serialize_message(msg), catalog.ros_class(name))
    from io import BytesIO

    buffer = BytesIO()
    msg.serialize(buffer)
    back = catalog.ros_class(name)()
    back.deserialize(buffer.getvalue())
    return back


def check_type(catalog: TypeCatalog, name: str) -> str | None:
    conv = Converter(catalog, name)
    for variant in range(3):
        pb = conv.proto_class()
        fill(catalog, name, pb, variant)
        wire = pb.SerializeToString(deterministic=True)
        ros_msg = conv.to_ros(conv.proto_class.FromString(wire))
        parsed = ros_wire_round_trip(catalog, name, ros_msg)
        again = conv.to_proto(parsed).SerializeToString(deterministic=True)
        if again != wire:
            a, b = conv.proto_class.FromString(wire), conv.proto_class.FromString(again)
            return f"variant {variant}: differs after the round trip:\nsent {str(a)[:1500]}\ngot {str(b)[:1500]}"
    return None


def misfit(catalog: TypeCatalog, name: str, setter: Any) -> str:
    conv = Converter(catalog, name)
    pb = conv.proto_class()
    setter(pb)
    try:
        conv.to_ros(pb)
    except ConversionError as exc:
        return str(exc)
    return "accepted"


def main() -> int:
    ros, packages = int(sys.argv[1]), sys.argv[2:]
    catalog = TypeCatalog(ros)
    types: dict[str, str | None] = {}
    for name in expand(packages, ros):
        try:
            types[name] = check_type(catalog, name)
        except Exception:  # reported per type, with its traceback
            types[name] = traceback.format_exc()
    misfits: dict[str, str] = {}
    m, k = ("msg/", "k") if ros == 2 else ("", "K")
    misfits["uint8 over 255"] = misfit(catalog, f"sensor_msgs/{m}Image", lambda pb: setattr(pb, "is_bigendian", 256))
    misfits["int8 under -128"] = misfit(catalog, f"std_msgs/{m}Int8", lambda pb: setattr(pb, "data", -129))
    misfits["fixed array too short"] = misfit(catalog, f"sensor_msgs/{m}CameraInfo",
                                              lambda pb: getattr(pb, k).extend([1.0] * 8))
    misfits["nested fixed array"] = misfit(catalog, f"geometry_msgs/{m}PoseWithCovarianceStamped",
                                           lambda pb: pb.pose.covariance.extend([0.0] * 35))
    misfits["int16 in an array"] = misfit(catalog, f"std_msgs/{m}Int16MultiArray",
                                          lambda pb: pb.data.extend([1, 40000]))
    print(json.dumps({"types": types, "misfits": misfits}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
