"""A fuzzer of the shared-memory session socket: frames a client library would never send, straight to a real server.

Connections to a `cast serve` process's session socket (docs/client-protocol.md, "Large values by
shared memory") send, with and without a valid HELLO first: random write requests in WRITES frames
(their staged values pointing in, at the edge of and past the session's staging area, or naming
another session), truncated and bit-flipped WRITES, RELEASE and RECEIVED frames with forged ids
and wrong sizes, unknown kinds, lengths past each kind's bound, memory files nobody asked for,
frames cut into single bytes, a second HELLO. Meanwhile two well-behaved components on the same
host write and watch a large value by shared memory, and one of them holds a view of it the whole
time, whose lease a forged RELEASE must not end.

Judged: the server stays up and keeps serving; it never logs a traceback or an unhandled error;
a session it ends is told why (REFUSED); the good components' every value arrives, in order and
unchanged, and the held view still reads its bytes; once the fuzzing connections are gone, the
server holds no more descriptors than before them.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import random
import socket
import struct
import threading
import time
from collections.abc import Iterator

import grpc
from google.protobuf.wrappers_pb2 import BytesValue
from grpc_health.v1 import health_pb2, health_pb2_grpc

import cast
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire import shared_memory as wire
from tests.conftest import ServerHandle, wait_for
from tests.reliability.figures import record, soak
from tests.reliability.random_messages import random_message

SIZE = 256 << 10  # over the shared-memory threshold (64 KiB): the good components' value goes by shared memory
GOOD_SA = "language"
FUZZ_SA = "vision"
_OPERATIONS = ["add", "overwrite", "delete", "batch", "lock", "unlock", "get"]


def _good_value(seed: int) -> BytesValue:
    """The good writer's value ``seed``: the seed, then one byte repeated, so a reader checks every byte cheaply."""
    return BytesValue(value=seed.to_bytes(8, "little") + bytes([seed % 251]) * (SIZE - 8))


def _intact(data: bytes | memoryview) -> int:
    """The seed of a good value whose every byte is as written; AssertionError naming the first changed byte."""
    seed = int.from_bytes(data[:8], "little")
    body = bytes(data[8:])
    expected = bytes([seed % 251]) * (SIZE - 8)
    if body != expected:
        at = next(i for i, (a, b) in enumerate(zip(body, expected, strict=True)) if a != b)
        raise AssertionError(f"value {seed}: byte {8 + at} is {body[at]}, not {seed % 251}")
    return seed


class _Connection:
    """One raw connection to the session socket, reading whatever the server sends (descriptors closed)."""

    def __init__(self, server: ServerHandle, token: str) -> None:
        channel = grpc.insecure_channel(server.endpoint)
        try:
            info = dir_grpc.DirectoryStub(channel).DescribeSystem(
                dir_pb2.DescribeSystemRequest(), metadata=(("authorization", f"Bearer {token}"),), timeout=10
            ).shared_memory
        finally:
            channel.close()
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect("\0" + info.socket)
        self.reader = wire.FrameReader()
        self.kinds: list[int] = []  # the kinds of the frames the server sent
        self.answers: list[str] = []  # each reply to a request: its result's kind, or its error's code
        self.refused = ""  # why the server ended the session, if it said
        self.ended = False  # the server closed the connection (read to its end)
        self.broken = False  # a send failed: the server closed its end
        self.session = b""
        self.staging_size = 0

    def send(self, data: bytes, fd: int | None = None) -> bool:
        """Send bytes (with a descriptor); False once the server closed the connection."""
        if self.broken or self.ended:
            return False
        self.sock.setblocking(True)
        try:
            if fd is None:
                self.sock.sendall(data)
            else:
                wire.send(self.sock, data, fd)
        except OSError:
            self.broken = True
        return not self.broken

    def read(self, wait: float = 0.0) -> None:
        """Read what the server sent, waiting up to ``wait`` s for the first bytes."""
        if wait:
            self.sock.settimeout(wait)
        else:
            self.sock.setblocking(False)
        while not self.ended:
            try:
                data, fds = wire.receive(self.sock)
            except (BlockingIOError, TimeoutError, InterruptedError):
                return
            except (OSError, wire.ProtocolError):
                self.ended = True
                return
            if not data:
                self.ended = True
                return
            for frame in self.reader.feed(data, fds):
                self._handle(frame)
            self.sock.setblocking(False)

    def _handle(self, frame: wire.Frame) -> None:
        self.kinds.append(frame.kind)
        if frame.kind == wire.WELCOME:
            _, self.session, _, _, _, self.staging_size = wire.parse_welcome(frame.body)
            assert frame.fd is not None
            self.staging = mmap.mmap(frame.fd, self.staging_size)
        elif frame.kind == wire.REFUSED:
            self.refused = frame.body.decode(errors="replace")
        elif frame.kind == wire.REPLIES:
            for reply in wm_pb2.WriteReplies.FromString(frame.body).replies:
                which = reply.WhichOneof("result") or "nothing"
                self.answers.append(reply.error.code if which == "error" else which)
        if frame.fd is not None:
            os.close(frame.fd)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()
        for fd in self.reader.stray():
            os.close(fd)
        staging = getattr(self, "staging", None)
        if staging is not None:
            staging.close()


def _staged(rng: random.Random, c: _Connection, others: list[bytes]) -> wm_pb2.StagedValue:
    """A staged value: inside the staging area, at its edge or past it, of this session or not, with random bytes."""
    size = c.staging_size
    session = rng.choice([c.session] * 6 + [others[0]] * 2 + rng.sample(others, min(2, len(others)))
                         + [rng.randbytes(16), b"", rng.randbytes(3)])
    offset = rng.choice([0, 0, 4096, size - 1, size, size + 1, rng.randrange(size), 2**63, 2**64 - 1])
    length = rng.choice([0, 1, 7, 64 << 10, SIZE, size, size + 1, 2**63, rng.randrange(1, 1 << 20)])
    if session == c.session and offset < size:
        end = min(size, offset + min(length, 1 << 20))
        # Mostly a serialised BytesValue (a value that passes), sometimes garbage, at the offset named.
        body = BytesValue(value=rng.randbytes(16) * ((end - offset) // 32)).SerializeToString()[: end - offset]
        c.staging[offset:offset + len(body)] = body if rng.random() < 0.7 else rng.randbytes(len(body))
    return wm_pb2.StagedValue(session=session, offset=offset, size=length)


def _requests(rng: random.Random, c: _Connection, others: list[bytes]) -> bytes:
    """A WRITES body of random requests: edge values in every field, staged values that go anywhere."""
    message = wm_pb2.WriteRequests()
    fields = wm_pb2.WriteRequest.DESCRIPTOR.fields_by_name
    for _ in range(rng.randrange(1, 5)):
        request = wm_pb2.WriteRequest(id=rng.choice([rng.randrange(1, 1000), 0, 2**64 - 1]),
                                      timeout_ms=rng.choice([0, 0, 1, 50]))
        # One operation each, drawn evenly (a random message would mostly set the oneof's last member), or none.
        which = rng.choice([*_OPERATIONS, None])
        if which is not None:
            message_type = fields[which].message_type
            assert message_type is not None
            getattr(request, which).CopyFrom(random_message(message_type, rng))
        if which not in (None, "batch") and rng.random() < 0.6:
            # An entry of its own SA, so that some requests pass the rules and reach the write itself.
            address = getattr(request, which).address
            address.subarchitecture, address.id = FUZZ_SA, rng.choice(["fz-a", "fz-b", "fz-c"])
        if which in ("add", "overwrite") and rng.random() < 0.7:
            body = getattr(request, which)
            if rng.random() < 0.8:
                body.value.type_url = "type.googleapis.com/google.protobuf.BytesValue"
            if rng.random() < 0.4:  # inline
                body.ClearField("staged_value")
                body.value.value = BytesValue(value=rng.randbytes(rng.choice([0, 8, 1000]))).SerializeToString()
            else:  # staged, somewhere
                body.value.value = b""
                body.staged_value.CopyFrom(_staged(rng, c, others))
        if rng.random() < 0.3:
            request.read_call = rng.choice([1, 2, 3, 2**64 - 1])
        message.requests.append(request)
    return message.SerializeToString()


def _corrupt(rng: random.Random, body: bytes) -> bytes:
    """``body`` cut short or with a few bits flipped."""
    out = bytearray(body)
    if rng.random() < 0.5 or not out:
        return bytes(out[: rng.randrange(len(out) + 1)])
    for _ in range(rng.randrange(1, 4)):
        out[rng.randrange(len(out))] ^= 1 << rng.randrange(8)
    return bytes(out)


def _frames(rng: random.Random, c: _Connection, others: list[bytes]) -> Iterator[tuple[bytes, int | None, bool]]:
    """Frames a client should never send, and valid ones among them: (bytes, descriptor to attach, split).

    Mostly frames a server answers and goes on after (random write requests, forged ids), so that a
    session lives long enough to reach the write path; a few that end it.
    """
    while True:
        pick = rng.random()
        if pick < 0.6:  # random requests, staged values anywhere
            yield wire.writes(_requests(rng, c, others)), None, False
        elif pick < 0.72:  # values given back that this session was never lent (other sessions' ids among them)
            ids = [rng.choice([rng.randrange(1, 4000), rng.randrange(2**64), 0]) for _ in range(rng.randrange(1, 40))]
            yield wire.encode(wire.RELEASE, struct.pack(f"<{len(ids)}Q", *ids)), None, False
        elif pick < 0.79:  # calls it never made, counts it never received
            body = struct.pack("<QQB", rng.choice([0, 1, 2, 3, 2**64 - 1]), rng.choice([0, 1, 10**6, 2**64 - 1]),
                               rng.choice([0, 1, 255]))
            yield wire.encode(wire.RECEIVED, body), None, False
        elif pick < 0.84:
            yield wire.encode(wire.NUDGE), None, False
        elif pick < 0.89:  # a memory file nobody asked for
            fd = os.memfd_create("fuzz") if rng.random() < 0.5 else os.open("/dev/null", os.O_RDONLY)
            yield wire.writes(_requests(rng, c, others)), fd, False
        elif pick < 0.94:  # one byte per send
            yield wire.writes(_requests(rng, c, others)), None, True
        else:  # each of these ends the session
            fatal = rng.randrange(8)
            if fatal == 0:
                yield wire.writes(_corrupt(rng, _requests(rng, c, others))), None, False
            elif fatal == 1:
                yield wire.encode(wire.RELEASE, rng.randbytes(rng.choice([1, 7, 9, 15]))), None, False
            elif fatal == 2:
                yield wire.encode(wire.RECEIVED, rng.randbytes(rng.choice([0, 16, 18]))), None, False
            elif fatal == 3:
                yield wire.encode(wire.NUDGE, rng.randbytes(rng.randrange(1, 5))), None, False
            elif fatal == 4:
                kind = rng.choice([0, 6, 9, 10, 12, 15, 99, 255])
                yield wire.encode(kind, rng.randbytes(rng.randrange(20))), None, False
            elif fatal == 5:
                yield wire.hello("not a token"), None, False
            else:
                kind = rng.choice([wire.RELEASE, wire.WRITES, wire.NUDGE])
                length = rng.choice([0, wire.MAX_FRAME + 1, wire.MAX_WRITES_FRAME + 1, 2**32 - 1])
                yield struct.pack("<IB", length, kind) + rng.randbytes(rng.randrange(8)), None, False


def _fuzz_one(rng: random.Random, server: ServerHandle, token: str, others: list[bytes], frames: int) -> _Connection:
    """One connection: a HELLO (broken sometimes), then up to ``frames`` frames until the server ends it."""
    c = _Connection(server, token)
    hello = rng.random()
    if hello < 0.08:
        c.send(wire.encode(wire.WRITES, b"\x0a\x00"))  # no HELLO first
    elif hello < 0.12:
        c.send(wire.encode(wire.HELLO, b"\x00"))  # too short
    elif hello < 0.16:
        c.send(wire.encode(wire.HELLO, struct.pack("<H", rng.choice([0, 3, 65535])) + token.encode()))
    elif hello < 0.2:
        c.send(wire.hello(token[:-4] + "AAAA"))
    else:
        c.send(wire.hello(token))
    c.read(wait=10)
    if not c.session:
        assert c.refused, f"a broken HELLO was not refused with a reason: kinds {c.kinds}"
        return c
    others.append(c.session)
    reads = rng.random() < 0.9  # a tenth read nothing until the end: their replies wait on the server
    for data, fd, split in _frames(rng, c, others):
        if frames <= 0 or c.ended or c.broken:
            break
        frames -= 1
        if split:
            sent = all(c.send(data[i:i + 1]) for i in range(len(data)))
        else:
            sent = c.send(data, fd)
        if fd is not None:
            os.close(fd)
        if not sent:
            break
        if reads:
            c.read()
    if rng.random() < 0.5:
        c.send(wire.writes(_requests(rng, c, others))[: rng.randrange(1, 8)])  # ends inside a frame
    c.read(wait=0.2)
    if reads and (c.ended or c.broken):
        c.read(wait=5)
        # The server ended it: it said why, as the last frame.
        assert c.refused and c.kinds[-1] == wire.REFUSED, f"a session ended without REFUSED: kinds {c.kinds[-5:]}"
    return c


def _socket_kinds() -> dict[str, str]:
    """Every socket's inode -> its family (unix, tcp), from /proc/net."""
    kinds: dict[str, str] = {}
    for family, column in (("unix", 6), ("tcp", 9), ("tcp6", 9)):
        with contextlib.suppress(OSError), open(f"/proc/net/{family}") as f:
            for line in f.readlines()[1:]:
                fields = line.split()
                if len(fields) > column:
                    kinds[fields[column]] = family
    return kinds


def _server_fds(server: ServerHandle) -> dict[str, int]:
    """The server's descriptors by kind (unix or TCP socket, memory file by name, pipe...), how many of each.

    The arena's segments are left out: the fuzzers' large values stay in the
    working memory's history, which the arena holds (bounded by history_bytes).
    """
    kinds: dict[str, int] = {}
    sockets = _socket_kinds()
    for fd in os.listdir(f"/proc/{server.process.pid}/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/{server.process.pid}/fd/{fd}")
            if target.startswith("/memfd:cast-arena"):
                continue
            if target.startswith("socket:["):
                kind = "socket:" + sockets.get(target[8:-1], "?")
            elif target.startswith("/memfd:"):
                kind = target.split(" ")[0]  # a staging area's, or one a client sent
            else:
                kind = target.split(":")[0]
            kinds[kind] = kinds.get(kind, 0) + 1
    return kinds


def test_fuzzing_the_shared_memory_socket_ends_only_the_fuzzed_sessions_and_the_server_keeps_serving(
    server: ServerHandle,
) -> None:
    # One fixed seed in `make test` (the same inputs every run); `make soak` draws one, printed for a rerun with
    # CAST_FUZZ_SEED.
    seed = int(os.environ.get("CAST_FUZZ_SEED") or (random.randrange(2**32) if soak() else 20261204))
    print(f"session fuzz seed {seed} (rerun with CAST_FUZZ_SEED={seed})")
    rng = random.Random(seed)
    connections, frames = (600, 80) if soak() else (120, 40)
    writer = server.connect("good-writer", GOOD_SA)
    watcher = server.connect("good-watcher", GOOD_SA)
    fuzz_token = server.token("fuzzer", FUZZ_SA)
    seen: list[int] = []
    broken: list[str] = []

    def arrived(change: cast.WorkingMemoryChange) -> None:
        if change.operation is cast.Operation.DELETE:
            return
        try:
            with change.view() as view:
                seen.append(_intact(view.field(1)))
                if not view.shared:
                    broken.append(f"value {seen[-1]} came as bytes: the good components lost their session")
        except AssertionError as exc:
            broken.append(str(exc))

    watcher.on_change(cast.address_filter("good-img", include_entry=True), arrived)
    writer.add("good-img", _good_value(0))
    held = watcher.get_view("good-img")  # a lease the fuzzers' forged RELEASEs must not end
    assert held.shared, "the good components have no shared-memory session: nothing here would be fuzzed"
    wait_for(lambda: seen == [0], what="the good watcher's first value")
    before = _server_fds(server)

    stop = threading.Event()
    written: list[int] = [0]

    def write_on() -> None:
        seed = 0
        while not stop.is_set():
            seed += 1
            writer.overwrite("good-img", _good_value(seed))
            written.append(seed)
            time.sleep(0.005)

    good = threading.Thread(target=write_on)
    good.start()
    refused: dict[str, int] = {}
    answers: dict[str, int] = {}
    # Sessions to name in staged values: the good writer's (live, another component's), then each fuzzer's.
    others: list[bytes] = [writer._transport._directory.shared.session().id]  # type: ignore[attr-defined]
    failures: list[BaseException] = []
    tally = threading.Lock()

    def fuzz(rng: random.Random, count: int) -> None:
        try:
            for _ in range(count):
                c = _fuzz_one(rng, server, fuzz_token, others, frames)
                try:
                    with tally:
                        if c.refused:
                            reason = c.refused.split(":")[0][:60]
                            refused[reason] = refused.get(reason, 0) + 1
                        for answer in c.answers:
                            answers[answer] = answers.get(answer, 0) + 1
                finally:
                    c.close()
                assert server.process.poll() is None, "the server died"
        except BaseException as exc:  # reported on the test's thread
            failures.append(exc)

    # Three fuzzers at once, each with its own inputs drawn from the seed, so sessions meet on the server.
    fuzzers = [threading.Thread(target=fuzz, args=(random.Random(rng.randrange(2**32)), connections // 3))
               for _ in range(3)]
    try:
        for t in fuzzers:
            t.start()
        for t in fuzzers:
            t.join(timeout=600)
    finally:
        stop.set()
        good.join(timeout=30)
    if failures:
        raise failures[0]

    # The good components: every value, in order, every byte as written; the held view unchanged.
    wait_for(lambda: len(seen) == len(written), timeout=30, what="the good watcher's every value")
    assert not broken, broken[:5]
    assert seen == written
    assert _intact(held.field(1)) == 0
    held.release()
    writer.overwrite("good-img", _good_value(10**6))
    assert _intact(watcher.get_view("good-img").field(1)) == 10**6
    channel = grpc.insecure_channel(server.endpoint)
    try:
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=5)
    finally:
        channel.close()
    assert health.status == health_pb2.HealthCheckResponse.SERVING
    # Nothing left of the fuzzing connections: no descriptor (socket, staging area) outlives them.
    wait_for(lambda: sum(_server_fds(server).values()) <= sum(before.values()), timeout=15,
             what=f"the server's descriptors back to {before} (now {_server_fds(server)})")
    unhandled = [line for line in server.log_lines
                 if "Traceback" in line or "Exception in callback" in line or "ERROR" in line]
    assert not unhandled, "".join(unhandled[:20])
    # Every request answered with a result or a refusal naming what was wrong, never a server fault.
    assert not {"INTERNAL", "UNKNOWN", "nothing"} & answers.keys(), answers
    assert answers.get("write") and answers.get("INVALID_ARGUMENT"), f"the write path was not reached: {answers}"
    assert refused, "no session was refused: the fuzzer sent nothing a server must refuse"
    record("session_fuzz", {"seed": seed, "connections": connections, "frames_each": frames,
                            "good_values": len(written), "answers": answers, "refused": refused})
    writer._cast_close()
    watcher._cast_close()

