"""Random protobuf messages with edge values, for the fuzzers of the gRPC wire and of the shared-memory socket."""

from __future__ import annotations

import random
from typing import Any

from google.protobuf import descriptor
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message
from google.protobuf.message_factory import GetMessageClass

__all__ = ["random_message", "random_value"]

_INTS = [0, 1, -1, 2, 255, 2**31 - 1, -(2**31), 2**32 - 1]
_UINTS = [0, 1, 2, 3, 4, 255, 2**31 - 1, 2**32 - 1, 2**63 - 1, 2**64 - 1]
_STRINGS = ["", "vision", "language", "x", "a" * 300, "\x00", "\u2603", "id/with/slash", "pkg.Message",
            "cast.testing.Counter", "type.googleapis.com/cast.testing.Counter", "\x7f\x01", "é" * 200]


def random_value(field: FieldDescriptor, rng: random.Random, depth: int) -> Any:
    """A value for ``field``: edge values mostly (limits, empty, NaN, odd strings), sometimes random."""
    t = field.type
    if t == FieldDescriptor.TYPE_MESSAGE:
        assert field.message_type is not None  # a message field always has its type
        return random_message(field.message_type, rng, depth + 1)
    if t in (FieldDescriptor.TYPE_STRING,):
        return rng.choice(_STRINGS) if rng.random() < 0.8 else "".join(chr(rng.randrange(1, 0x2FF)) for _ in range(8))
    if t == FieldDescriptor.TYPE_BYTES:
        return rng.randbytes(rng.choice([0, 1, 7, 64, 1000]))
    if t == FieldDescriptor.TYPE_BOOL:
        return rng.random() < 0.5
    if t == FieldDescriptor.TYPE_ENUM:
        assert field.enum_type is not None  # an enum field always has its type
        values = [v.number for v in field.enum_type.values]
        return rng.choice([*values, 99, -5])
    if t in (FieldDescriptor.TYPE_UINT32, FieldDescriptor.TYPE_FIXED32):
        return rng.choice([v for v in _UINTS if v < 2**32])
    if t in (FieldDescriptor.TYPE_UINT64, FieldDescriptor.TYPE_FIXED64):
        return rng.choice(_UINTS)
    if t in (FieldDescriptor.TYPE_INT64, FieldDescriptor.TYPE_SINT64, FieldDescriptor.TYPE_SFIXED64):
        return rng.choice([*_INTS, -(2**63), 2**63 - 1])
    if t in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
        return rng.choice([0.0, -1.5, 1e300, float("nan")])
    return rng.choice(_INTS)


def random_message(desc: descriptor.Descriptor, rng: random.Random, depth: int = 0) -> Message:
    """A message of ``desc`` with about two thirds of its fields set to :func:`random_value`s, nested to depth 3."""
    msg = GetMessageClass(desc)()
    if depth > 3:
        return msg
    for field in desc.fields:
        if rng.random() < 0.35:
            continue
        try:
            if field.message_type is not None and field.message_type.GetOptions().map_entry:
                key_f, val_f = field.message_type.fields_by_name["key"], field.message_type.fields_by_name["value"]
                target = getattr(msg, field.name)
                for _ in range(rng.randrange(3)):
                    key = random_value(key_f, rng, depth)
                    if val_f.type == FieldDescriptor.TYPE_MESSAGE:
                        target[key].CopyFrom(random_value(val_f, rng, depth))
                    else:
                        target[key] = random_value(val_f, rng, depth)
            elif field.is_repeated:
                target = getattr(msg, field.name)
                for _ in range(rng.randrange(4)):
                    value = random_value(field, rng, depth)
                    if field.type == FieldDescriptor.TYPE_MESSAGE:
                        target.add().CopyFrom(value)
                    else:
                        target.append(value)
            elif field.type == FieldDescriptor.TYPE_MESSAGE:
                getattr(msg, field.name).CopyFrom(random_value(field, rng, depth))
            else:
                setattr(msg, field.name, random_value(field, rng, depth))
        except (ValueError, TypeError):
            pass  # a value the Python runtime refuses to set (e.g. invalid UTF-8): skip the field
    return msg
