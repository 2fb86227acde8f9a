"""EVENTS frames decoded in C give what protobuf gives: the same records, claims, errors, in the same order.

cast.client._events_native (python/cast/client/events_native.c) is built by
the compiled build (make mypyc), where these tests run in `make test`; run
from the editable checkout they build it themselves with the C compiler, so
the C decoder is what they test either way. Every field of the messages an
event is made of is filled from the schema itself, so a field added to
proto/cast/v1 that the pure path turns into a record attribute and the C
decoder does not fails here.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
from collections.abc import Iterator
from types import ModuleType
from typing import Any

import pytest
from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import Message

from cast.client import conversions
from cast.client.shm_session import ReadCall
from cast.core.records import ChangeEvent, EntryRecord, Operation
from cast.errors import UnavailableError
from cast.v1 import entry_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from tests.client.native_build import INSTALLED, ROOT, native_module


@pytest.fixture(scope="module")
def native(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """The C decoder: the build's own, or (an editable checkout has none) built here from its source."""
    module, installed = native_module("_events_native", tmp_path_factory)
    if not installed:  # the build's own is configured by cast.client.conversions
        module.configure(ChangeEvent, EntryRecord, {int(op): op for op in Operation}, Operation)
    return module


class _Session:
    """What a ReadCall uses of its session: claims answered from a fake segment, frames sent kept."""

    id = b"\x01" * 16

    def __init__(self, fail_at: int = 0) -> None:
        self.claims: list[tuple[int, int, int, int]] = []
        self.sent: list[bytes] = []
        self.fail_at = fail_at

    def send(self, frame: bytes) -> None:
        self.sent.append(frame)

    def claim_at(self, segment: int, offset: int, size: int, value_id: int) -> tuple[memoryview, object]:
        self.claims.append((segment, offset, size, value_id))
        if len(self.claims) == self.fail_at:
            raise UnavailableError(f"segment {segment} never came")
        return memoryview(bytes([value_id % 251]) * 3), ("lease", value_id)


def _record(obj: Any) -> Any:
    """Every slot of a record, bytes for its data, nested records likewise (comparable with ==)."""
    if isinstance(obj, ChangeEvent | EntryRecord):
        names = getattr(type(obj), "__slots__", None) or type(obj).__mypyc_attrs__  # the compiled build's classes
        return (type(obj).__name__, {s: _record(getattr(obj, s)) for s in names})
    if isinstance(obj, memoryview):
        return ("view", obj.readonly, bytes(obj))
    return obj


def _turn(body: bytes, how: ModuleType | None, fail_at: int = 0) -> dict[str, Any]:
    """What turning ``body`` gives one way (``how``: the C decoder, or None for protobuf)."""
    session = _Session(fail_at)
    call = ReadCall(session, 7)  # type: ignore[arg-type]
    sunk: list[Any] = []
    seen: dict[str, int] = {"other": 5}
    error: str | None = None

    def sink(event: ChangeEvent, watch_ids: Any) -> None:
        sunk.append((_record(event), list(watch_ids)))

    try:
        if how is None:
            saved, conversions._native = conversions._native, None
            try:
                conversions.turn_events(body, call, sink, seen)
            finally:
                conversions._native = saved
        elif not how.turn(body, call.claim_at, sink, seen):
            return {"declined": True, "events": sunk, "claims": session.claims}
    except Exception as exc:  # compared between the two paths
        error = f"{type(exc).__name__}: {exc}"
    return {"events": sunk, "seen": seen, "claims": session.claims, "count": call.count, "error": error}


def _fill(msg: Message, serial: Iterator[int]) -> None:
    """Set every field of ``msg`` and of the messages in it, each to a value no other field has."""
    descriptor: Descriptor = msg.DESCRIPTOR
    for field in descriptor.fields:
        values = [_value(msg, field, serial) for _ in range(2 if field.is_repeated else 1)]
        if field.type == FieldDescriptor.TYPE_MESSAGE:
            for _ in values:
                target = getattr(msg, field.name).add() if field.is_repeated \
                    else getattr(msg, field.name)
                _fill(target, serial)
        elif field.is_repeated:
            getattr(msg, field.name).extend(values)
        else:
            setattr(msg, field.name, values[0])


def _value(msg: Message, field: FieldDescriptor, serial: Iterator[int]) -> Any:
    n = next(serial)
    if field.type == FieldDescriptor.TYPE_STRING:
        return f"{field.name}-{n}-é"  # not ASCII: the UTF-8 decoding is compared too
    if field.type == FieldDescriptor.TYPE_BYTES:
        return bytes([n % 256]) * (n % 7 + 1)
    if field.type == FieldDescriptor.TYPE_ENUM:
        return field.enum_type.values[-1].number
    if field.type == FieldDescriptor.TYPE_BOOL:
        return True
    if field.type in (FieldDescriptor.TYPE_INT32, FieldDescriptor.TYPE_SINT32, FieldDescriptor.TYPE_SFIXED32):
        return -1000 * n if field.name != "nanos" else 1000 * n
    if field.type in (FieldDescriptor.TYPE_UINT32, FieldDescriptor.TYPE_FIXED32):
        return 2**31 + n
    if field.type in (FieldDescriptor.TYPE_INT64, FieldDescriptor.TYPE_SINT64, FieldDescriptor.TYPE_SFIXED64):
        return 1_700_000_000 + n
    if field.type in (FieldDescriptor.TYPE_UINT64, FieldDescriptor.TYPE_FIXED64):
        return 2**40 + n
    if field.type == FieldDescriptor.TYPE_MESSAGE:
        return None
    raise AssertionError(f"{msg.DESCRIPTOR.full_name}.{field.name}: no value for its type {field.type}")


def _full_response() -> wm_pb2.WatchResponse:
    """Three events: every field set (a lent value), every field set but the lent value, no entry."""
    serial = iter(range(1, 10_000))
    resp = wm_pb2.WatchResponse()
    for _ in range(3):
        _fill(resp.events.add(), serial)
    resp.events[1].entry.ClearField("shared_value")
    resp.events[2].ClearField("entry")
    resp.events[2].skipped = 0  # the event's own skipped counts stay 0 then
    for event in resp.events:
        event.operation = Operation.OVERWRITE
    return resp


def test_every_field_of_the_schema_reaches_the_same_records(native: ModuleType) -> None:
    body = _full_response().SerializeToString()
    pure, fast = _turn(body, None), _turn(body, native)
    assert pure["error"] is None and len(pure["events"]) == 3 and len(pure["claims"]) == 1
    assert fast == pure
    event = fast["events"][0][0][1]
    assert event["skipped"] > 0 and event["first_skipped_revision"] > 0 and event["time_ns"] > 0
    assert fast["seen"][event["subarchitecture"]] == event["revision"] and fast["seen"]["other"] == 5


def test_empty_fields_and_an_empty_frame_give_defaults(native: ModuleType) -> None:
    resp = wm_pb2.WatchResponse()
    event = resp.events.add(operation=Operation.ADD)
    event.entry.shared_value.SetInParent()  # present though empty: still a lent value to claim
    resp.events.add(operation=Operation.DELETE).entry.SetInParent()
    for body in (resp.SerializeToString(), b""):
        pure = _turn(body, None)
        assert _turn(body, native) == pure and pure["error"] is None
    assert len(_turn(resp.SerializeToString(), native)["claims"]) == 1


def test_packed_and_unpacked_watch_ids_both_read(native: ModuleType) -> None:
    resp = wm_pb2.WatchResponse()
    resp.events.add(revision=3, operation=Operation.ADD, watch_ids=[4, 2**32 - 1])
    packed = resp.SerializeToString()
    # the same ids one field each (tag 10, varint): protobuf's parsers accept both forms
    event = entry_pb2.ChangeEvent(revision=3, operation=Operation.ADD).SerializeToString()
    unpacked_event = event + bytes([0x50, 4]) + bytes([0x50]) + _varint(2**32 - 1)
    unpacked = bytes([0x0A]) + _varint(len(unpacked_event)) + unpacked_event
    for body in (packed, unpacked):
        fast = _turn(body, native)
        assert fast == _turn(body, None) and fast["events"][0][1] == [4, 2**32 - 1]
    empty_packed = bytes([0x0A, len(event) + 2]) + event + bytes([0x52, 0])  # tag 10, length 0: no ids
    fast = _turn(empty_packed, native)
    assert fast == _turn(empty_packed, None) and fast["events"][0][1] == []


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        out.append((n & 0x7F) | (0x80 if n > 0x7F else 0))
        n >>= 7
        if not n:
            return bytes(out)


def test_what_it_does_not_decode_exactly_is_left_to_protobuf(native: ModuleType) -> None:
    """Declined, with nothing claimed or handed on: the pure path then answers (a merge, or its error)."""
    event = entry_pb2.ChangeEvent(revision=9, operation=Operation.ADD)
    event.address.subarchitecture = "vision"
    twice = event.SerializeToString() + entry_pb2.ChangeEvent(
        address=entry_pb2.ChangeEvent().address.__class__(id="img")).SerializeToString()  # address given twice
    declined = {
        "a message field given twice (protobuf merges)": bytes([0x0A]) + _varint(len(twice)) + twice,
        "another field of WatchResponse": wm_pb2.WatchResponse(cancelled=[3]).SerializeToString(),
        "a group": bytes([0x0A, 2, 0x6B, 0x6C]),
        "a string that is not UTF-8": bytes([0x0A, 4, 0x22, 2, 0xFF, 0xFE]),
        "a length past the end": bytes([0x0A, 9, 0x08, 1]),
        "a varint past the end": bytes([0x0A, 2, 0x08, 0x80]),
    }
    for what, body in declined.items():
        assert _turn(body, native) == {"declined": True, "events": [], "claims": []}, what
    merged = _turn(declined["a message field given twice (protobuf merges)"], None)
    assert merged["events"][0][0][1]["subarchitecture"] == "vision" and merged["events"][0][0][1]["id"] == "img"
    assert _turn(declined["a string that is not UTF-8"], None)["error"] is not None


def test_a_failed_claim_ends_it_after_the_events_before(native: ModuleType) -> None:
    resp = wm_pb2.WatchResponse()
    for revision in (11, 12, 13):
        e = resp.events.add(revision=revision, operation=Operation.OVERWRITE)
        e.address.subarchitecture = "vision"
        e.entry.shared_value.value_id = revision
    body = resp.SerializeToString()
    pure, fast = _turn(body, None, fail_at=2), _turn(body, native, fail_at=2)
    assert fast == pure
    assert len(fast["events"]) == 1 and fast["seen"]["vision"] == 11 and "never came" in fast["error"]


def test_an_unknown_operation_fails_before_its_value_is_claimed(native: ModuleType) -> None:
    resp = wm_pb2.WatchResponse()
    resp.events.add(revision=1, operation=Operation.ADD).entry.shared_value.value_id = 1
    resp.events.add(revision=2, operation=9).entry.shared_value.value_id = 2  # type: ignore[arg-type]
    body = resp.SerializeToString()
    pure, fast = _turn(body, None), _turn(body, native)
    assert fast == pure and len(fast["claims"]) == 1 and fast["error"].startswith("ValueError")


def test_changed_bytes_give_what_protobuf_gives(native: ModuleType) -> None:
    """Frames with bytes flipped, cut or added: where the C decoder takes one, it turns it as protobuf does."""
    body = _full_response().SerializeToString()
    rng = random.Random(20261203)
    taken = 0
    for _ in range(3000):
        changed = bytearray(body)
        for _ in range(rng.randint(1, 3)):
            at = rng.randrange(len(changed) + 1)
            what = rng.random()
            if what < 0.6 and at < len(changed):
                changed[at] = rng.randrange(256)
            elif what < 0.8:
                del changed[at:]
            else:
                changed[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 4)))
        fast = _turn(bytes(changed), native)
        if fast.get("declined"):
            assert not fast["events"] and not fast["claims"], changed.hex()
        else:
            taken += 1
            assert fast == _turn(bytes(changed), None), changed.hex()
    assert taken > 100  # the comparison ran on many frames, not only on declined ones


@pytest.mark.parametrize("setting", ["", "0"])
def test_the_build_decides_and_one_setting_turns_it_off(setting: str) -> None:
    """Native in the compiled build (pure in an editable checkout); CAST_NATIVE_EVENTS=0 keeps the pure path."""
    env = {k: v for k, v in os.environ.items() if k != "CAST_NATIVE_EVENTS"}
    if setting:
        env["CAST_NATIVE_EVENTS"] = setting
    if not INSTALLED:
        env["PYTHONPATH"] = str(ROOT / "python")
    out = subprocess.run(
        [sys.executable, "-c", "from cast.client import conversions; print(conversions.NATIVE_EVENTS)"],
        env=env, capture_output=True, text=True, check=True,
    ).stdout.strip()
    assert out == str(INSTALLED and setting != "0")
