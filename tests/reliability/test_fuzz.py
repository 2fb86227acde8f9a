"""A wire fuzzer: malformed bytes, truncated and oversized messages and random field values, sent
straight to every RPC through a raw channel. The server answers every call with a status and keeps
serving, and its state stays consistent (a valid client still works afterwards)."""

from __future__ import annotations

import random
from typing import Any

import grpc
from google.protobuf import descriptor
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message
from google.protobuf.message_factory import GetMessageClass
from grpc_health.v1 import health_pb2, health_pb2_grpc

from tests.conftest import ServerHandle
from tests.reliability.figures import record, soak
from tests.reliability.rawcalls import Method, call, methods

_INTS = [0, 1, -1, 2, 255, 2**31 - 1, -(2**31), 2**32 - 1]
_UINTS = [0, 1, 2, 3, 4, 255, 2**31 - 1, 2**32 - 1, 2**63 - 1, 2**64 - 1]
_STRINGS = ["", "vision", "language", "x", "a" * 300, "\x00", "\u2603", "id/with/slash", "pkg.Message",
            "cast.testing.Counter", "type.googleapis.com/cast.testing.Counter", "\x7f\x01", "é" * 200]


def _random_value(field: FieldDescriptor, rng: random.Random, depth: int) -> Any:
    t = field.type
    if t == FieldDescriptor.TYPE_MESSAGE:
        return _random_message(field.message_type, rng, depth + 1)
    if t in (FieldDescriptor.TYPE_STRING,):
        return rng.choice(_STRINGS) if rng.random() < 0.8 else "".join(chr(rng.randrange(1, 0x2FF)) for _ in range(8))
    if t == FieldDescriptor.TYPE_BYTES:
        return rng.randbytes(rng.choice([0, 1, 7, 64, 1000]))
    if t == FieldDescriptor.TYPE_BOOL:
        return rng.random() < 0.5
    if t == FieldDescriptor.TYPE_ENUM:
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


def _random_message(desc: descriptor.Descriptor, rng: random.Random, depth: int = 0) -> Message:
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
                    key = _random_value(key_f, rng, depth)
                    if val_f.type == FieldDescriptor.TYPE_MESSAGE:
                        target[key].CopyFrom(_random_value(val_f, rng, depth))
                    else:
                        target[key] = _random_value(val_f, rng, depth)
            elif field.is_repeated:
                target = getattr(msg, field.name)
                for _ in range(rng.randrange(4)):
                    value = _random_value(field, rng, depth)
                    if field.type == FieldDescriptor.TYPE_MESSAGE:
                        target.add().CopyFrom(value)
                    else:
                        target.append(value)
            elif field.type == FieldDescriptor.TYPE_MESSAGE:
                getattr(msg, field.name).CopyFrom(_random_value(field, rng, depth))
            else:
                setattr(msg, field.name, _random_value(field, rng, depth))
        except (ValueError, TypeError):
            pass  # a value the Python runtime refuses to set (e.g. invalid UTF-8): skip the field
    return msg


def _inputs(method: Method, rng: random.Random, count: int) -> list[list[bytes]]:
    """Payloads for one method: valid-but-random messages, their truncations and bit flips, random bytes."""
    out: list[list[bytes]] = []
    for i in range(count):
        valid = _random_message(method.request, rng).SerializeToString()
        kind = i % 5
        if kind == 0:
            payload = valid
        elif kind == 1:
            payload = valid[: rng.randrange(len(valid) + 1)]  # truncated
        elif kind == 2 and valid:
            flipped = bytearray(valid)
            for _ in range(rng.randrange(1, 4)):
                flipped[rng.randrange(len(flipped))] ^= 1 << rng.randrange(8)
            payload = bytes(flipped)
        elif kind == 3:
            payload = rng.randbytes(rng.choice([1, 3, 16, 200]))  # garbage
        else:
            payload = bytes([0x0A, 0xFF, 0xFF, 0xFF, 0x0F]) + rng.randbytes(4)  # length far past the end
        out.append([payload] if not method.client_streaming else [payload] * rng.randrange(1, 4))
    return out


def test_fuzzing_every_rpc_gets_a_status_and_the_server_keeps_serving(server: ServerHandle) -> None:
    rng = random.Random(20261122)
    per_unary, per_stream = (400, 60) if soak() else (40, 8)
    channel = grpc.insecure_channel(server.endpoint, options=[("grpc.max_send_message_length", 80 * 1024 * 1024)])
    md = (("authorization", f"Bearer {server.token('fuzzer', 'vision', privileged=True)}"),)
    tried = 0
    statuses: dict[str, int] = {}
    try:
        for method in methods():
            streaming = method.client_streaming or method.server_streaming
            for payloads in _inputs(method, rng, per_stream if streaming else per_unary):
                code, _, _ = call(channel, method, payloads, md, timeout=0.5 if streaming else 5.0)
                tried += 1
                statuses[code.name] = statuses.get(code.name, 0) + 1
                if not streaming:
                    # A unary call always gets a server status, never a client-side timeout.
                    assert code != grpc.StatusCode.DEADLINE_EXCEEDED, method.path
                assert code != grpc.StatusCode.UNKNOWN, (method.path, payloads, call(channel, method, payloads, md))
        # Oversized: a message past the server's 64 MiB limit is refused, not processed.
        add = next(m for m in methods() if m.name == "Add")
        code, _, _ = call(channel, add, [b"\x12\x00" + b"\x00" * (65 * 1024 * 1024)], md, timeout=30)
        tried += 1
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED
        # Still serving: health, and a proper write and read.
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=5)
        assert health.status == health_pb2.HealthCheckResponse.SERVING
        writer = server.connect("after-fuzz", "vision")
        from cast_testing_pb2 import Counter

        writer.add("still-fine", Counter(value=1))
        assert writer.get("still-fine", Counter).value == 1
        writer._cast_close()
    finally:
        channel.close()
    assert server.process.poll() is None, "the server died"
    internal = statuses.get("INTERNAL", 0)
    record("wire_fuzz", {"inputs": tried, "methods": len(methods()), "statuses": statuses})
    assert internal == 0, f"{internal} calls failed with INTERNAL (a server bug): {statuses}"
