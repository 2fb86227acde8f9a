"""Field-by-field conversion between ROS messages and their protobuf entry types, both ways, with range checks.

ROS -> protobuf cannot lose anything: every ROS value has a protobuf type that
holds it (``descriptors``). Protobuf -> ROS can meet values ROS cannot hold: a
``uint32`` over 255 for a ROS ``uint8``, a fixed array of the wrong length, a
bounded string or array that is too long. Those are refused with a
:class:`ConversionError` naming the field (``header.frame_id``, ``k``) and the
limit, and nothing is published. rclpy checks none of this itself unless
``ROS_PYTHON_CHECK_FIELDS=1``: a wrong value would reach the wire.

The two ROS generations hold values differently (rclpy: ``array.array`` for
sequences of numbers, numpy arrays for fixed arrays, ``bytes`` of one for a
``byte``; genpy: lists, ``bytes`` for ``uint8[]``, ``genpy.Time``); each has a
:class:`_Values` of its own and everything else is shared.
"""

from __future__ import annotations

import array
from collections.abc import Callable
from typing import Any

from google.protobuf import message

from cast.bridges.ros.catalog import TypeCatalog
from cast.bridges.ros.model import INT_RANGES, MESSAGE_KIND, Field, FieldType

__all__ = ["ConversionError", "Converter"]

_TYPECODES = {"int8": "b", "uint8": "B", "int16": "h", "uint16": "H", "int32": "i", "uint32": "I",
              "int64": "q", "uint64": "Q", "float32": "f", "float64": "d"}


class ConversionError(ValueError):
    """A value that does not fit its ROS field: ``field`` is its path (``header.frame_id``), the text the limit."""

    def __init__(self, field: str, text: str) -> None:
        super().__init__(f"field {field}: {text}")
        self.field = field
        self.text = text


class _Values:
    """How one ROS generation's classes hold arrays and bytes (ROS 1, genpy: plain Python values)."""

    def bytes_in(self, value: Any) -> bytes:
        if isinstance(value, bytes):
            return value
        if isinstance(value, (bytearray, memoryview, array.array)) or hasattr(value, "tobytes"):
            return bytes(value) if not hasattr(value, "tobytes") else value.tobytes()
        if value and isinstance(value[0], bytes):  # rclpy: a byte[] read back as a list of bytes objects
            return b"".join(value)
        return bytes(value)

    def bytes_out(self, t: FieldType, data: bytes) -> Any:
        return data

    def numbers_out(self, t: FieldType, values: list[Any]) -> Any:
        return values

    def scalar_in(self, t: FieldType, value: Any) -> Any:
        return value

    def scalar_out(self, t: FieldType, value: Any) -> Any:
        return value


class _Ros2Values(_Values):
    """rclpy: ``array.array`` for sequences of numbers, numpy arrays for fixed ones, ``bytes`` for a byte."""

    def __init__(self) -> None:
        import numpy

        self._numpy = numpy

    def bytes_out(self, t: FieldType, data: bytes) -> Any:
        if t.kind == "octet":
            return data if t.array != "fixed" else [data[i:i + 1] for i in range(len(data))]
        if t.array == "fixed":
            return self._numpy.frombuffer(data, dtype=self._numpy.uint8).copy()
        return array.array("B", data)

    def numbers_out(self, t: FieldType, values: list[Any]) -> Any:
        code = _TYPECODES.get(t.kind)
        if code is None:
            if t.kind in ("char", "wchar"):
                return [chr(v) for v in values]
            return values
        if t.array == "fixed":
            return self._numpy.array(values, dtype=self._numpy.dtype(t.kind))
        return array.array(code, values)

    def scalar_in(self, t: FieldType, value: Any) -> Any:
        if t.kind == "octet":
            return value[0] if isinstance(value, (bytes, bytearray)) else int(value)
        if t.kind in ("char", "wchar"):
            return ord(value) if isinstance(value, str) else int(value)
        return value

    def scalar_out(self, t: FieldType, value: Any) -> Any:
        if t.kind == "octet":
            return bytes([value])
        if t.kind in ("char", "wchar"):
            return chr(value)
        return value


def _length_check(path: str, t: FieldType, n: int, unit: str) -> None:
    if t.array == "fixed" and n != t.size:
        raise ConversionError(path, f"{n} {unit} for a fixed array of exactly {t.size} ({t.ros_text()})")
    if t.array == "bounded" and n > t.size:
        raise ConversionError(path, f"{n} {unit} for a bounded array of at most {t.size} ({t.ros_text()})")


def _int_check(path: str, kind: str, value: int) -> None:
    lo, hi = INT_RANGES[kind]
    if not lo <= value <= hi:
        raise ConversionError(path, f"{value} does not fit a ROS {kind if kind != 'octet' else 'byte'} "
                                    f"({lo} to {hi})")


def _string_check(path: str, t: FieldType, value: str) -> None:
    if t.string_bound and len(value) > t.string_bound:
        raise ConversionError(path, f"a string of {len(value)} characters for {t.ros_text()} "
                                    f"(at most {t.string_bound})")


def _utf8(path: str, value: Any) -> str:
    if isinstance(value, str):
        return value
    try:
        return bytes(value).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConversionError(path, f"the ROS string is not UTF-8 ({exc}), which a protobuf string must be") from None


class Converter:
    """Converts one ROS message type (and the types it nests) to its protobuf class and back."""

    def __init__(self, catalog: TypeCatalog, name: str) -> None:
        self.catalog = catalog
        self.name = name
        self.proto_class = catalog.proto_class(name)
        self._values: _Values = _Ros2Values() if catalog.ros == 2 else _Values()
        self._to_proto: dict[str, list[Callable[[message.Message, Any, str], None]]] = {}
        self._to_ros: dict[str, list[Callable[[Any, message.Message, str], None]]] = {}

    # ------------------------------------------------------------ to protobuf

    def to_proto(self, ros_message: Any) -> message.Message:
        """The protobuf message of a ROS message; ConversionError for a ROS 1 string that is not UTF-8."""
        out = self.proto_class()
        self._fill_proto(self.name, out, ros_message, "")
        return out

    def _fill_proto(self, name: str, out: message.Message, ros_message: Any, prefix: str) -> None:
        ops = self._to_proto.get(name)
        if ops is None:
            ops = self._to_proto[name] = [self._proto_op(f) for f in self.catalog.describe(name).fields]
        for op in ops:
            op(out, ros_message, prefix)

    def _proto_op(self, f: Field) -> Callable[[message.Message, Any, str], None]:
        name, t, values = f.name, f.type, self._values
        if t.kind == MESSAGE_KIND:
            nested = t.message
            if t.array:
                def messages(out: message.Message, ros: Any, prefix: str) -> None:
                    repeated = getattr(out, name)
                    for i, item in enumerate(getattr(ros, name)):
                        self._fill_proto(nested, repeated.add(), item, f"{prefix}{name}[{i}].")
                return messages

            def one(out: message.Message, ros: Any, prefix: str) -> None:
                self._fill_proto(nested, getattr(out, name), getattr(ros, name), f"{prefix}{name}.")
            return one
        if t.is_bytes:
            def data(out: message.Message, ros: Any, prefix: str) -> None:
                setattr(out, name, values.bytes_in(getattr(ros, name)))
            return data
        if t.kind in ("string", "wstring"):
            if t.array:
                def strings(out: message.Message, ros: Any, prefix: str) -> None:
                    getattr(out, name).extend(_utf8(prefix + name, s) for s in getattr(ros, name))
                return strings

            def string(out: message.Message, ros: Any, prefix: str) -> None:
                setattr(out, name, _utf8(prefix + name, getattr(ros, name)))
            return string
        if t.array:
            def numbers(out: message.Message, ros: Any, prefix: str) -> None:
                v = getattr(ros, name)
                items = v.tolist() if hasattr(v, "tolist") else v
                getattr(out, name).extend(values.scalar_in(t, x) for x in items)
            return numbers

        def scalar(out: message.Message, ros: Any, prefix: str) -> None:
            setattr(out, name, values.scalar_in(t, getattr(ros, name)))
        return scalar

    # ----------------------------------------------------------------- to ROS

    def to_ros(self, value: message.Message) -> Any:
        """The ROS message of a protobuf one; ConversionError naming the field and the limit of a misfit."""
        return self._make_ros(self.name, value, "")

    def _make_ros(self, name: str, value: message.Message, prefix: str) -> Any:
        ops = self._to_ros.get(name)
        if ops is None:
            ops = self._to_ros[name] = [self._ros_op(f) for f in self.catalog.describe(name).fields]
        out = self.catalog.ros_class(name)()
        for op in ops:
            op(out, value, prefix)
        return out

    def _ros_op(self, f: Field) -> Callable[[Any, message.Message, str], None]:
        name, t, values = f.name, f.type, self._values
        if t.kind == MESSAGE_KIND:
            nested = t.message
            if t.array:
                def messages(out: Any, pb: message.Message, prefix: str) -> None:
                    items = getattr(pb, name)
                    _length_check(prefix + name, t, len(items), "messages")
                    setattr(out, name, [self._make_ros(nested, item, f"{prefix}{name}[{i}].")
                                        for i, item in enumerate(items)])
                return messages

            def one(out: Any, pb: message.Message, prefix: str) -> None:
                setattr(out, name, self._make_ros(nested, getattr(pb, name), f"{prefix}{name}."))
            return one
        if t.is_bytes:
            def data(out: Any, pb: message.Message, prefix: str) -> None:
                raw = getattr(pb, name)
                _length_check(prefix + name, t, len(raw), "bytes")
                setattr(out, name, values.bytes_out(t, raw))
            return data
        if t.kind in ("string", "wstring"):
            if t.array:
                def strings(out: Any, pb: message.Message, prefix: str) -> None:
                    items = list(getattr(pb, name))
                    _length_check(prefix + name, t, len(items), "strings")
                    for i, s in enumerate(items):
                        _string_check(f"{prefix}{name}[{i}]", t, s)
                    setattr(out, name, items)
                return strings

            def string(out: Any, pb: message.Message, prefix: str) -> None:
                s = getattr(pb, name)
                _string_check(prefix + name, t, s)
                setattr(out, name, s)
            return string
        checked = t.kind in INT_RANGES and t.kind not in ("int32", "int64", "uint32", "uint64")
        if t.array:
            def numbers(out: Any, pb: message.Message, prefix: str) -> None:
                items = list(getattr(pb, name))
                _length_check(prefix + name, t, len(items), "values")
                if checked:
                    lo, hi = INT_RANGES[t.kind]
                    for i, x in enumerate(items):
                        if not lo <= x <= hi:
                            _int_check(f"{prefix}{name}[{i}]", t.kind, x)
                setattr(out, name, values.numbers_out(t, items))
            return numbers

        def scalar(out: Any, pb: message.Message, prefix: str) -> None:
            x = getattr(pb, name)
            if checked:
                _int_check(prefix + name, t.kind, x)
            setattr(out, name, values.scalar_out(t, x))
        return scalar

