"""A wire fuzzer: malformed bytes, truncated and oversized messages and random field values, sent
straight to every RPC through a raw channel. The server answers every call with a status and keeps
serving, and its state stays consistent (a valid client still works afterwards)."""

from __future__ import annotations

import random

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

from tests.conftest import ServerHandle
from tests.reliability.figures import record, soak
from tests.reliability.random_messages import random_message
from tests.reliability.rawcalls import Method, call, methods


def _inputs(method: Method, rng: random.Random, count: int) -> list[list[bytes]]:
    """Payloads for one method: valid-but-random messages, their truncations and bit flips, random bytes."""
    out: list[list[bytes]] = []
    for i in range(count):
        valid = random_message(method.request, rng).SerializeToString()
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
