"""The schema check leaves large ``bytes`` fields out of its parse, and its verdict is the full parse's.

A ``google.protobuf.Any`` has a string (``type_url``, field 1: proto3 checks its
UTF-8) and a ``bytes`` field (``value``, field 2): the string after, before or
around a large value must still be checked, and a value that is not a message
must still be refused.
"""

from __future__ import annotations

import pytest
from google.protobuf import any_pb2, wrappers_pb2
from google.protobuf.message import DecodeError
from hypothesis import given, settings
from hypothesis import strategies as st

from cast.core.large_fields import LARGE, bytes_fields, without_large_bytes
from cast.core.schemas import SchemaRegistry
from cast.errors import InvalidArgumentError

ANY = "google.protobuf.Any"
BIG = b"\x07" * (1 << 20)
REG = SchemaRegistry()


def _field(number: int, payload: bytes) -> bytes:
    """A length-delimited field (number < 16, payload under 2**21)."""
    n, length = len(payload), bytearray()
    while True:
        length.append((n & 0x7F) | (0x80 if n >= 0x80 else 0))
        n >>= 7
        if not length[-1] & 0x80:
            return bytes([number << 3 | 2]) + bytes(length) + payload


def _verdict(data: bytes) -> bool:
    """Whether the protobuf runtime parses ``data`` as an Any, the whole of it."""
    try:
        any_pb2.Any.FromString(data)
    except DecodeError:
        return False
    return True


def test_a_large_bytes_field_is_emptied_and_the_rest_kept_in_order() -> None:
    data = _field(1, b"type.googleapis.com/x") + _field(2, BIG) + _field(1, b"after")
    lighter = without_large_bytes(data, bytes_fields(any_pb2.Any.DESCRIPTOR))
    assert lighter == _field(1, b"type.googleapis.com/x") + b"\x12\x00" + _field(1, b"after")
    assert without_large_bytes(_field(2, b"x" * (LARGE - 1)), frozenset({2})) is None  # small: parsed as it is
    assert without_large_bytes(_field(1, BIG), frozenset({2})) is None  # a string field is never emptied


def test_a_large_value_of_a_registered_type_passes_parsed_without_its_bytes(monkeypatch: pytest.MonkeyPatch) -> None:
    parsed: list[int] = []
    real = any_pb2.Any.FromString

    def spy(data: bytes) -> any_pb2.Any:
        parsed.append(len(data))
        return real(data)

    reg = SchemaRegistry()
    reg.validate("google.protobuf.BytesValue", wrappers_pb2.BytesValue(value=BIG).SerializeToString())
    reg._classes[ANY] = type("Spy", (), {"FromString": staticmethod(spy)})  # type: ignore[assignment]
    reg.validate(ANY, memoryview(any_pb2.Any(type_url="t/x", value=BIG).SerializeToString()))
    assert parsed == [len(_field(1, b"t/x")) + 2]  # the type_url and an empty value: not the megabyte


@pytest.mark.parametrize(
    "data",
    [
        _field(1, b"\xff\xfe") + _field(2, BIG),  # invalid UTF-8 before the large field
        _field(2, BIG) + _field(1, b"\xc3"),  # ... after it
        _field(2, BIG)[:-1],  # the large field runs past the end
        _field(2, BIG) + b"\x0a\x05ab",  # a field after it runs past the end
        _field(2, BIG) + b"\x0b",  # a group start after it
        _field(1, b"\xff" * (1 << 20)),  # a large string field is checked whole
    ],
    ids=["utf8-before", "utf8-after", "truncated", "truncated-after", "group", "large-string"],
)
def test_what_the_full_parse_refuses_is_still_refused(data: bytes) -> None:
    assert not _verdict(data)
    with pytest.raises(InvalidArgumentError, match="does not parse as google.protobuf.Any"):
        REG.validate(ANY, data)


@settings(max_examples=60)
@given(st.lists(st.tuples(st.sampled_from([1, 2, 3]),
                          st.sampled_from([b"ok", b"\xff", b"z" * LARGE, b"y" * (4 * LARGE)])), max_size=4),
       st.integers(min_value=0, max_value=8))
def test_the_verdict_is_the_full_parses(fields: list[tuple[int, bytes]], cut: int) -> None:
    data = b"".join(_field(number, payload) for number, payload in fields)
    data = data[: len(data) - cut] if cut else data  # sometimes truncated
    try:
        REG.validate(ANY, data)
        ok = True
    except InvalidArgumentError:
        ok = False
    assert ok == _verdict(data)
