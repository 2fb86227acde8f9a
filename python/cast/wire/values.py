"""Values on the wire: entry types as type URLs in ``Any``, and timestamps."""

from __future__ import annotations

from google.protobuf import any_pb2, timestamp_pb2

from cast.errors import InvalidArgumentError

__all__ = ["TYPE_URL_PREFIX", "any_of", "any_to_type_data", "ns", "put_varint", "timestamp", "varint"]

TYPE_URL_PREFIX = "type.googleapis.com/"


def put_varint(out: bytearray, n: int) -> None:
    """Append ``n`` (0 or more) to ``out`` as a protobuf varint."""
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)


def varint(n: int) -> bytes:
    """``n`` (0 or more) as a protobuf varint: what a length or a field's key is on the wire."""
    out = bytearray()
    put_varint(out, n)
    return bytes(out)


def timestamp(ns: int) -> timestamp_pb2.Timestamp:
    """A Timestamp from nanoseconds since the epoch."""
    return timestamp_pb2.Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def ns(ts: timestamp_pb2.Timestamp) -> int:
    """Nanoseconds since the epoch of a Timestamp."""
    return ts.seconds * 1_000_000_000 + ts.nanos


def any_to_type_data(value: any_pb2.Any, what: str = "value") -> tuple[str, bytes]:
    """(type name, bytes) of an Any; INVALID_ARGUMENT if it names no type."""
    url = value.type_url
    if not url:
        raise InvalidArgumentError(
            f"{what} has no type_url: pack a protobuf message into the Any (Any.Pack) so the entry has a type"
        )
    return url[url.rfind("/") + 1 :], value.value


def any_of(type_name: str, data: bytes) -> any_pb2.Any:
    """An Any holding ``data`` of type ``type_name``."""
    return any_pb2.Any(type_url=TYPE_URL_PREFIX + type_name, value=data)
