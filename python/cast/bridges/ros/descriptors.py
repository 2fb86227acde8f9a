"""Protobuf descriptors of ROS message types, built at run time from the model.

One ``.proto`` file per ROS type (``ros2/sensor_msgs/msg/image.proto``),
importing the files of the types it nests: the same files, by meaning, as
protoc makes of the text ``protofile`` writes, so the schemas the bridge
registers and those a C++ or Java component compiled in agree (the server
compares them by meaning, ``cast.core.schema_compare``).

The mapping of each field (docs/ros.md, "What maps"):

=====================================  ==========================================
ROS                                    protobuf
=====================================  ==========================================
bool                                   bool
int8, int16, int32                     int32 (range-checked on the way to ROS)
uint8, uint16, uint32, byte, char      uint32 (range-checked)
int64 / uint64                         int64 / uint64
float32 / float64                      float / double
string, wstring (bounded too)          string (bound checked on the way to ROS)
uint8[] and byte[] (any array kind)    bytes (length checked for fixed / bounded)
other T[], T[N], T[<=N]                repeated T (length checked)
a nested message, Time, Duration       the nested message type
=====================================  ==========================================
"""

from __future__ import annotations

from collections.abc import Iterable

from google.protobuf import descriptor_pb2, descriptor_pool, message, message_factory

from cast.bridges.ros.model import MESSAGE_KIND, FieldType, MessageType, proto_file, proto_name, proto_package

__all__ = ["PROTO_TYPES", "build_classes", "file_proto", "java_outer_classname", "proto_scalar"]

FieldProto = descriptor_pb2.FieldDescriptorProto

# The protobuf scalar type of each model kind (arrays of BYTES_KINDS are one `bytes` instead).
PROTO_TYPES: dict[str, tuple[FieldProto.Type.ValueType, str]] = {
    "bool": (FieldProto.TYPE_BOOL, "bool"),
    "int8": (FieldProto.TYPE_INT32, "int32"),
    "int16": (FieldProto.TYPE_INT32, "int32"),
    "int32": (FieldProto.TYPE_INT32, "int32"),
    "int64": (FieldProto.TYPE_INT64, "int64"),
    "uint8": (FieldProto.TYPE_UINT32, "uint32"),
    "uint16": (FieldProto.TYPE_UINT32, "uint32"),
    "uint32": (FieldProto.TYPE_UINT32, "uint32"),
    "uint64": (FieldProto.TYPE_UINT64, "uint64"),
    "octet": (FieldProto.TYPE_UINT32, "uint32"),
    "char": (FieldProto.TYPE_UINT32, "uint32"),
    "wchar": (FieldProto.TYPE_UINT32, "uint32"),
    "float32": (FieldProto.TYPE_FLOAT, "float"),
    "float64": (FieldProto.TYPE_DOUBLE, "double"),
    "string": (FieldProto.TYPE_STRING, "string"),
    "wstring": (FieldProto.TYPE_STRING, "string"),
}


def proto_scalar(t: FieldType) -> tuple[FieldProto.Type.ValueType, str]:
    """The protobuf type (enum value and .proto spelling) of a non-message field, arrays of bytes included."""
    if t.is_bytes:
        return FieldProto.TYPE_BYTES, "bytes"
    return PROTO_TYPES[t.kind]


def java_outer_classname(t: MessageType) -> str:
    """The Java outer class of a type's file: ``<Name>OuterClass``, protoc's own choice when names clash."""
    return proto_name(t.name, t.ros).rsplit(".", 1)[1] + "OuterClass"


def file_proto(t: MessageType) -> descriptor_pb2.FileDescriptorProto:
    """The ``.proto`` file of one ROS type, as protoc would describe the text ``protofile`` writes."""
    fd = descriptor_pb2.FileDescriptorProto(
        name=proto_file(t.name, t.ros), package=proto_package(t.name, t.ros), syntax="proto3")
    fd.dependency.extend(proto_file(dep, t.ros) for dep in t.dependencies())
    fd.options.java_multiple_files = True
    fd.options.java_package = fd.package
    fd.options.java_outer_classname = java_outer_classname(t)
    msg = fd.message_type.add(name=proto_name(t.name, t.ros).rsplit(".", 1)[1])
    for number, f in enumerate(t.fields, start=1):
        fp = msg.field.add(name=f.name, number=number, json_name=_json_name(f.name))
        repeated = bool(f.type.array) and not f.type.is_bytes
        fp.label = FieldProto.LABEL_REPEATED if repeated else FieldProto.LABEL_OPTIONAL
        if f.type.kind == MESSAGE_KIND:
            fp.type = FieldProto.TYPE_MESSAGE
            fp.type_name = "." + proto_name(f.type.message, t.ros)
        else:
            fp.type = proto_scalar(f.type)[0]
    return fd


def _json_name(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(part[:1].upper() + part[1:] for part in rest)


def build_classes(types: Iterable[MessageType]) -> dict[str, type[message.Message]]:
    """Message classes of ROS types (by ROS name), in a descriptor pool of their own.

    ``types`` must hold every type the others nest (``TypeCatalog.closure``).
    """
    pool = descriptor_pool.DescriptorPool()
    by_name = {t.name: t for t in types}
    added: set[str] = set()

    def add(t: MessageType) -> None:
        if t.name in added:
            return
        added.add(t.name)
        for dep in t.dependencies():
            add(by_name[dep])
        pool.Add(file_proto(t))

    for t in by_name.values():
        add(t)
    return {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(proto_name(name, t.ros)))
            for name, t in by_name.items()}
