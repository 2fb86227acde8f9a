"""A writer or a reader of large values, as a process of its own: the Python peer.

tests/reliability/test_shared_memory_processes.py and tests/interop/test_shared_memory_interop.py run
it; the C++ cast_test_shm and the Java cast.itest.ShmPeer take the same arguments and print the same
lines. With the launch contract (CAST_*) in its environment:

- ``shm_peer.py write N [change] [loan]``: adds "img" (or overwrites it if it exists) and
  overwrites it, N values of 1 MiB in all (value k is :func:`frame` ``(k)``), printing ``WROTE k`` after each and
  ``DONE`` at the end; then it stays until killed or its stdin closes. ``change``: once each write was
  acknowledged, it writes 0xFF over all of its staging area (the memory the value went through) and prints
  ``CHANGED k bytes`` (0 bytes: it has no staging area) before ``WROTE k``. ``loan``: each value is made in a
  loan (``Component.loan``) and the loan written.
- ``shm_peer.py read [hold|trywrite]``: watches "img" with its entry, printing
  ``WATCHING`` once the watch is confirmed and ``GOT revision k shared same sum`` per
  value (``k``: which frame the view's field 1 is, -1 for bytes that are no frame;
  ``shared``: 1 if it came by shared memory; ``same``: 1 if the decoded entry has the view's bytes; ``sum``: a
  checksum of every byte of the view, :func:`checksum`), and ``MISMATCH revision`` when the view and the decoded
  entry differ. ``hold`` keeps a view of every value; ``trywrite`` tries, on the first value lent, to write the
  memory it is in and prints ``WRITE buffer=R pwrite=R mmap=R`` (R: how it was refused, ``allowed`` if it was
  not: through the view, and through the memory file opened again read-write by its /proc path), then
  ``AFTER k``. ``FAILED reason`` if the watch fails. It stays until killed or its stdin closes.
- ``shm_peer.py get``: reads "img" with get_view and get; prints ``READ k shared same``.
- ``shm_peer.py deadline SA MS``: two connections of its own (``cast.connect`` as ``$CAST_COMPONENT_ID-get`` and
  ``-add`` of ``$CAST_SUBARCHITECTURE``, tokens minted from ``$CAST_SECRET``, call timeout MS), no shared-memory
  session yet (the add connection wrote a small value of the type in its own SA: the type is registered); prints
  ``READY``, and at the line ``go`` on stdin a get and a 1 MiB add on SA at once, each
  ``CALL get|add ErrorName|ok milliseconds``, then ``CALLED``.
"""

from __future__ import annotations

import errno
import logging
import mmap
import os
import sys
import threading
import time
from collections.abc import Callable

from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client.runner import LaunchContract
from cast.errors import CastError

SIZE = 1 << 20


def frame(k: int) -> bytes:
    """The bytes of frame ``k``: a pattern that differs in every byte position from frame to frame."""
    return bytes((k * 7 + i) % 253 for i in range(253)) * (SIZE // 253)


def which(data: bytes) -> int:
    """The ``k`` of a frame's bytes, or -1."""
    k = next((k for k in range(256) if data[:16] == frame(k)[:16]), -1)
    return k if k >= 0 and data == frame(k) else -1


def checksum(data: memoryview) -> int:
    """Every byte read: ``sum = sum * 31 + byte`` modulo 2**64, as the C++ and Java peers compute it."""
    total = 0
    for b in data:
        total = (total * 31 + b) & 0xFFFFFFFFFFFFFFFF
    return total


def say(line: str, lock: threading.Lock = threading.Lock()) -> None:  # noqa: B008 - one lock for every line
    """One line on stdout, whole: one write, so that a log line on stderr (the same pipe) cannot land inside it."""
    with lock:
        sys.stdout.write(line + "\n")  # print() writes the line and its end apart, unbuffered (PYTHONUNBUFFERED)
        sys.stdout.flush()


def memory_files(kind: str) -> list[str]:
    """The /proc/self/map_files paths of this process's mappings of the server's ``kind`` memory files."""
    with open("/proc/self/maps") as maps:
        return [f"/proc/self/map_files/{line.split()[0]}" for line in maps if f"memfd:cast-{kind}" in line]


def change_staging() -> int:
    """Write 0xFF over every staging area this process has mapped; the bytes written."""
    written = 0
    for path in memory_files("staging"):
        fd = os.open(path, os.O_RDWR)
        try:
            size = os.fstat(fd).st_size
            os.pwrite(fd, b"\xff" * size, 0)
            written += size
        finally:
            os.close(fd)
    return written


def refusal(exc: BaseException) -> str:
    """How a write was refused: the errno name, or the error's type."""
    number = getattr(exc, "errno", None)
    return errno.errorcode.get(number, type(exc).__name__) if isinstance(number, int) else type(exc).__name__


def try_write(view: cast.ValueView) -> str:
    """Try to write the memory a lent value is in: through the view, and through its memory file."""
    out = ["WRITE"]
    try:
        view.data[0] = 0x55  # type: ignore[index]  # a read-only memoryview: the point is that this fails
        out.append("buffer=allowed")
    except TypeError as exc:
        out.append(f"buffer={type(exc).__name__}")
    files = memory_files("arena")
    if not files:
        return " ".join([*out, "pwrite=nofile", "mmap=nofile"])
    try:
        fd = os.open(files[0], os.O_RDWR)
    except OSError as exc:
        return " ".join([*out, f"pwrite=open:{refusal(exc)}", f"mmap=open:{refusal(exc)}"])
    try:
        try:
            os.pwrite(fd, b"\x55", 0)
            out.append("pwrite=allowed")
        except OSError as exc:
            out.append(f"pwrite={refusal(exc)}")
        try:
            mmap.mmap(fd, mmap.PAGESIZE, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE).close()
            out.append("mmap=allowed")
        except OSError as exc:
            out.append(f"mmap={refusal(exc)}")
    finally:
        os.close(fd)
    return " ".join(out)


class Peer(cast.UnmanagedComponent):
    """Says when its watch failed."""

    def watch_failed(self, error: cast.CastError) -> None:
        say(f"FAILED {error}")


def write(peer: Peer, frames: int, change: bool, loan: bool) -> None:
    for k in range(frames):
        value: BytesValue | cast.Loan = BytesValue(value=frame(k))
        if loan:
            value = peer.loan(BytesValue(), "value", len(frame(k)))
            value.buffer[:] = frame(k)
        peer.overwrite("img", value) if k or peer.exists("img") else peer.add("img", value)
        if change:
            say(f"CHANGED {k} {change_staging()}")
        say(f"WROTE {k}")
    say("DONE")


def read(peer: Peer, option: str) -> None:
    held: list[cast.ValueView] = []
    tried = threading.Event()

    def got(change: cast.WorkingMemoryChange) -> None:
        view = change.view()
        pixels = view.field(1)
        same = change.entry(BytesValue).value.value == bytes(pixels)
        say(f"GOT {change.revision} {which(bytes(pixels))} {int(view.shared)} {int(same)} {checksum(view.data)}")
        if not same:
            say(f"MISMATCH {change.revision}")
        if option == "trywrite" and view.shared and not tried.is_set():
            tried.set()
            say(try_write(view))
            say(f"AFTER {which(bytes(view.field(1)))}")
        if option == "hold":
            held.append(view)
        else:
            view.release()

    peer.on_change(cast.address_filter("img", cast.Operation.ADD, cast.Operation.OVERWRITE, include_entry=True), got)
    say("WATCHING")


def get(peer: Peer) -> None:
    with peer.get_view("img") as view:
        same = peer.get("img", BytesValue).value == bytes(view.field(1))
        say(f"READ {which(bytes(view.field(1)))} {int(view.shared)} {int(same)}")


def deadline(sa: str, timeout_ms: int) -> None:
    """Two fresh connections, then a get and a 1 MiB add at once at "go": how each ended, and when."""
    me, own = os.environ["CAST_COMPONENT_ID"], os.environ["CAST_SUBARCHITECTURE"]
    conns = [cast.connect(component_id=f"{me}-{name}", subarchitecture=own, call_timeout=timeout_ms / 1000)
             for name in ("get", "add")]
    # The value's type is registered with every server by the first write of it: done now, in the own SA, so that
    # the add below meets the stopped server first when it opens the session.
    conns[1].add(f"{me}-warm", BytesValue(value=b"warm"))
    calls: dict[str, Callable[[], object]] = {
        "get": lambda: conns[0].get("deadline", BytesValue, subarchitecture=sa),
        "add": lambda: conns[1].add("deadline", BytesValue(value=frame(0)), subarchitecture=sa),
    }
    say("READY")
    while sys.stdin.readline().strip() != "go":
        pass

    def timed(name: str, call: Callable[[], object]) -> None:
        started = time.monotonic()
        try:
            call()
            outcome = "ok"
        except CastError as exc:
            outcome = type(exc).__name__
        say(f"CALL {name} {outcome} {round((time.monotonic() - started) * 1000)}")

    threads = [threading.Thread(target=timed, args=item) for item in calls.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    say("CALLED")
    sys.stdin.read()
    for conn in conns:
        conn.close()


def main(mode: str, args: list[str]) -> None:
    logging.basicConfig(level=logging.INFO, format="%(name)s %(levelname)s %(message)s")  # the fallback's INFO line
    if mode == "deadline":
        deadline(args[0], int(args[1]))
        return
    peer = Peer()
    peer._cast_bind(LaunchContract.from_env().connect())
    if mode == "write":
        write(peer, int(args[0]), "change" in args[1:], "loan" in args[1:])
    elif mode == "read":
        read(peer, args[0] if args else "")
    elif mode == "get":
        get(peer)
    else:
        raise SystemExit("usage: shm_peer.py write N [change] [loan] | read [hold|trywrite] | get | deadline SA MS")
    sys.stdin.read()  # until the test closes it, or kills this process
    peer._cast_close()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
