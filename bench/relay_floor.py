"""M8's two-hop floor: a bare Python relay between one writer and four readers, on one host.

CAST's large values go writer -> server -> watcher: two hops, one copy by the
server into memory only it writes, the readers reading it in place. This is
that path with nothing else: no protobuf, no rules, no history, no versions.
The writer (in the benchmark's process) copies each value into a staging
memory file it shares with the relay and sends its size; the relay (a process,
``python -m bench.relay_floor relay NAME``, an asyncio loop as CAST's server)
copies it into a slot of an arena it alone writes, tells each reader where it
is and acknowledges the writer; each reader (``python -m bench.relay_floor sub
NAME DELAY INDEX``, a process) reads every byte where it lies (bench.checksum),
stamps it and gives the slot back. A slot is reused only once every reader
gave it back. Messages are SOCK_SEQPACKET datagrams on an abstract Unix socket
unique to the run; the memory files pass as ``SCM_RIGHTS``.

What it shows: what the architecture itself costs on the machine, in Python,
so that M8's figures can be read against it (the gap is CAST's own work per
frame, not the hops). No product's rival, and not a target.
"""

from __future__ import annotations

import asyncio
import mmap
import os
import select
import socket
import struct
import sys
import time
import uuid
from typing import Any

from bench.harness import PYTHON
from bench.peer_fanout import END, WARM, Receiver, Subscribers, drive, frame

__all__ = ["large"]

SLOTS = 8  # values the relay's arena holds: a ninth waits until every reader gave the oldest back
_SIZE = struct.Struct("<Q")  # writer -> relay: the staged value's size; relay -> writer: the same, as the ack
_WHERE = struct.Struct("<QQ")  # relay -> reader: slot, size
_HELLO_WRITER, _HELLO_READER = b"W", b"R"


def _seqpacket() -> socket.socket:
    return socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)


class _Writer:
    """The writer's side: a staging memory file shared with the relay; a put copies, sends, waits for the ack."""

    def __init__(self, size: int, subscribers: int, reader_delay_s: float) -> None:
        self.name = f"cast-bench-relay-{os.getpid()}-{uuid.uuid4().hex[:12]}"
        self.relay = Subscribers([PYTHON, "-m", "bench.relay_floor", "relay", self.name, str(size)], 1)
        self.subs: Subscribers | None = None
        try:
            self.relay.handshake(lambda: None)  # it prints "ready" once it listens
            fd = os.memfd_create("cast-bench-staging", os.MFD_CLOEXEC)
            os.ftruncate(fd, size)
            self.staging = mmap.mmap(fd, size)
            self.sock = _seqpacket()
            self.sock.connect("\0" + self.name)
            socket.send_fds(self.sock, [_HELLO_WRITER], [fd])
            os.close(fd)
            self.subs = Subscribers([PYTHON, "-m", "bench.relay_floor", "sub", self.name, str(reader_delay_s)],
                                    subscribers)
            warm = frame(WARM, 16)
            self.subs.handshake(lambda: self.put(warm))
        except BaseException:
            self.close()
            raise

    def put(self, payload: bytes) -> None:
        size = len(payload)
        self.staging[:size] = payload
        self.sock.sendall(_SIZE.pack(size))
        self.sock.recv(_SIZE.size)  # the relay's ack: the value is in its arena and the readers were told

    def close(self) -> None:
        if self.subs is not None:
            self.subs.close()
        self.relay.close()


def large(frames: int, gap_s: float, size: int, subscribers: int = 4, warm: int = 0,
          warm_size: int = 0, cold: int = 0, reader_delay_s: float = 0.0) -> dict[str, Any]:
    """M8's run through the bare relay: as :func:`bench.zenoh_peer.large` (the same frames, warm-up and pause).

    ``reader_delay_s``: each reader sleeps this long after each value it gave back (tests: a slow reader).
    """
    writer = _Writer(max(size, warm_size, 16), subscribers, reader_delay_s)
    try:
        sent = drive(writer.put, frames, gap_s, size, warm, warm_size, cold)
        writer.put(frame(END, 16))
        assert writer.subs is not None
        got = writer.subs.results()
    finally:
        writer.close()
    return {"sent": sent, "watchers": got}


class _Relay:
    """The relay's loop: accepts the writer and the readers, copies each staged value into a free slot."""

    def __init__(self, name: str, slot_bytes: int) -> None:
        self.slot_bytes = slot_bytes
        fd = os.memfd_create("cast-bench-arena", os.MFD_CLOEXEC)
        os.ftruncate(fd, slot_bytes * SLOTS)
        self.arena_fd = fd
        self.arena = memoryview(mmap.mmap(fd, slot_bytes * SLOTS))
        self.staging: memoryview | None = None
        self.writer: socket.socket | None = None
        self.readers: list[socket.socket] = []
        self.held = [0] * SLOTS  # readers yet to give each slot back
        self.next = 0
        self.waiting = 0  # the size of a staged value waiting for its slot (0: none)
        self.listener = _seqpacket()
        self.listener.bind("\0" + name)
        self.listener.listen(16)
        self.listener.setblocking(False)
        self.done = asyncio.get_running_loop().create_future()

    def accept(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            conn, _ = self.listener.accept()
        except BlockingIOError:
            return
        conn.setblocking(True)  # the writer and the readers send their hello as they connect: read at once
        hello, fds, _, _ = socket.recv_fds(conn, 16, 1)
        if hello == _HELLO_WRITER:
            self.staging = memoryview(mmap.mmap(fds[0], self.slot_bytes, prot=mmap.PROT_READ))
            os.close(fds[0])
            self.writer = conn
            loop.add_reader(conn.fileno(), self.staged)
        else:
            socket.send_fds(conn, [_SIZE.pack(self.slot_bytes * SLOTS)], [self.arena_fd])
            self.readers.append(conn)
            loop.add_reader(conn.fileno(), self.given_back, conn)

    def staged(self) -> None:
        assert self.writer is not None
        data = self.writer.recv(_SIZE.size)
        if not data:
            self.done.set_result(None)
            return
        (self.waiting,) = _SIZE.unpack(data)
        self.relay()

    def relay(self) -> None:
        slot = self.next
        if self.held[slot]:
            asyncio.get_running_loop().remove_reader(self.writer.fileno())  # type: ignore[union-attr]
            return  # the last reader to give the slot back relays it
        size, self.waiting = self.waiting, 0
        start = slot * self.slot_bytes
        assert self.staging is not None
        self.arena[start:start + size] = self.staging[:size]
        self.next = (slot + 1) % SLOTS
        where = _WHERE.pack(slot, size)
        for reader in self.readers:
            reader.send(where)
        self.held[slot] = len(self.readers)
        self.writer.send(_SIZE.pack(size))  # type: ignore[union-attr]

    def given_back(self, conn: socket.socket) -> None:
        data = conn.recv(_SIZE.size)
        if not data:
            asyncio.get_running_loop().remove_reader(conn.fileno())
            return
        (slot,) = _SIZE.unpack(data)
        self.held[slot] -= 1
        if self.waiting and not self.held[self.next]:
            self.relay()
            asyncio.get_running_loop().add_reader(self.writer.fileno(), self.staged)  # type: ignore[union-attr]


async def _relay_main(name: str, slot_bytes: int) -> None:
    relay = _Relay(name, slot_bytes)
    asyncio.get_running_loop().add_reader(relay.listener.fileno(), relay.accept)
    print("ready", flush=True)
    await relay.done


def _subscriber(name: str, delay_s: float) -> None:
    sock = _seqpacket()
    sock.connect("\0" + name)
    sock.send(_HELLO_READER)
    data, fds, _, _ = socket.recv_fds(sock, 16, 1)
    (arena_bytes,) = _SIZE.unpack(data)
    arena = memoryview(mmap.mmap(fds[0], arena_bytes, prot=mmap.PROT_READ))
    os.close(fds[0])
    slot_bytes = arena_bytes // SLOTS
    receiver = Receiver(read_all=True)
    poller = select.poll()
    poller.register(sock, select.POLLIN)
    while not receiver.done.is_set():
        poller.poll()
        slot, size = _WHERE.unpack(sock.recv(_WHERE.size))
        start = slot * slot_bytes
        receiver.on_message(arena[start:start + size])  # the relay's memory, read in place
        sock.send(_SIZE.pack(slot))
        if delay_s:
            time.sleep(delay_s)
    receiver.report()
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    if sys.argv[1] == "relay":
        asyncio.run(_relay_main(sys.argv[2], int(sys.argv[3])))
    elif sys.argv[1] == "sub":
        _subscriber(sys.argv[2], float(sys.argv[3]))
