"""Peers of large values by shared memory in every language, for tests/interop/test_shared_memory_interop.py.

A *peer* is a writer or a reader process with the launch contract in its environment; every
language's peer takes the same arguments and prints the same lines, so a test runs them alike:

- ``write N [change] [loan]``: ``WROTE k`` after each 1 MiB frame, ``DONE``; with ``change``, ``CHANGED k bytes``
  once write k was acknowledged and the writer wrote 0xFF over its whole staging area; with ``loan``, each frame
  made in a loan and the loan written;
- ``read [hold|trywrite]``: ``WATCHING``, then ``GOT revision k shared same sum`` per value (``k``: which
  frame the view's bytes are; ``shared``: 1 when lent by shared memory; ``same``: 1 when the decoded entry
  has the view's bytes; ``sum``: a checksum of every byte of the view, :func:`checksum`), ``FAILED reason``;
  ``trywrite``: ``WRITE way=how ...`` (each way it tried to write the memory it was lent, and how it was
  refused), then ``AFTER k``;
- ``get``: ``READ k shared same``;
- ``deadline SA MS``: two connections of its own with call timeout MS, ``READY``; at ``go`` on stdin a get
  and a 1 MiB add on SA at once, ``CALL get|add ErrorName|ok milliseconds`` each, ``CALLED``.

The peers: Python tests/reliability/components/shm_peer.py, C++ cast_test_shm
(cpp_client/tests/components/cast_test_shm.cc), Java cast.itest.ShmPeer
(java_client/src/test/java/cast/itest/ShmPeer.java). A language is one entry of :data:`PEERS`.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import grpc

from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import inspection_pb2_grpc as insp_grpc
from tests.conftest import ServerHandle
from tests.interop.cpp_support import cpp_executable
from tests.interop.java_support import java_classpath
from tests.netns import Lines

ROOT = Path(__file__).resolve().parents[2]
PYTHON_PEER = str(ROOT / "tests" / "reliability" / "components" / "shm_peer.py")

PEERS: dict[str, Callable[[], list[str]]] = {
    "python": lambda: [sys.executable, PYTHON_PEER],
    "cpp": lambda: [str(cpp_executable("cast_test_shm"))],
    "java": lambda: ["java", "-cp", java_classpath(), "cast.itest.ShmPeer"],
}
"""Each language's peer command (the build it needs is checked when it is asked for)."""

LANGUAGES = list(PEERS)
SIZE = 1 << 20


def frame(k: int) -> bytes:
    """The bytes of frame ``k`` (as every peer makes them)."""
    return bytes((k * 7 + i) % 253 for i in range(253)) * (SIZE // 253)


def checksum(data: bytes) -> int:
    """The checksum the peers compute over a view's bytes: ``sum = sum * 31 + byte``, modulo 2**64."""
    total = 0
    for b in data:
        total = (total * 31 + b) & 0xFFFFFFFFFFFFFFFF
    return total


def dev_shm_mapped(pid: int) -> list[str]:
    """The files of /dev/shm a process maps."""
    with open(f"/proc/{pid}/maps") as maps:
        return [line.split()[-1] for line in maps if "/dev/shm/" in line]


def mappings(pid: int) -> dict[str, list[str]]:
    """The permissions of each mapping of the server's memory files in a process (``memfd:cast-...`` name -> perms)."""
    out: dict[str, list[str]] = {}
    with open(f"/proc/{pid}/maps") as maps:
        for line in maps:
            if "memfd:cast-" in line:
                name = next(w for w in line.split() if w.startswith("/memfd:cast-")).split(":")[1]
                out.setdefault(name.split("-")[1], []).append(line.split()[1])
    return out


def shared(handle: ServerHandle) -> dict[str, Any]:
    """The server's shared-memory figures (what `cast stats` shows)."""
    with grpc.insecure_channel(handle.endpoint) as channel:
        pb = insp_grpc.InspectionStub(channel).GetMetrics(
            insp_pb2.GetMetricsRequest(), metadata=(("authorization", f"Bearer {handle.token('t', 'vision')}"),),
            timeout=10).shared_memory
    return {f.name: getattr(pb, f.name) for f in pb.DESCRIPTOR.fields}


def got(reader: Lines) -> list[tuple[int, int]]:
    """(frame, shared) of each value a reader printed."""
    return [(int(x.split()[2]), int(x.split()[3])) for x in reader.lines if x.startswith("GOT")]


def same_and_sums(reader: Lines) -> list[tuple[int, int]]:
    """(same, sum) of each value a reader printed."""
    return [(int(x.split()[4]), int(x.split()[5])) for x in reader.lines if x.startswith("GOT")]


def memory_files(pid: int) -> list[str]:
    """The lines of the server's memory files a process maps."""
    with open(f"/proc/{pid}/maps") as maps:
        return [line for line in maps if "memfd:cast-" in line]


class Peers:
    """The peer processes of one test, ended at its end."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen[str]] = []

    def start(self, language: str, handle: ServerHandle | None, cid: str, *args: str, prefix: Sequence[str] = (),
              env: dict[str, str] | None = None, base_env: dict[str, str] | None = None) -> Lines:
        """A peer of ``language`` as component ``cid`` of SA vision of ``handle``'s server (or with ``base_env``).

        ``prefix`` goes before its command, ``env`` is added to its environment.
        """
        if base_env is None:
            assert handle is not None, "a peer needs a server or a whole launch environment"
            base_env = handle.env(cid, "vision")
        environment = {**base_env, **(env or {})}
        proc = subprocess.Popen([*prefix, *PEERS[language](), *args], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=environment)
        self.procs.append(proc)
        return Lines(proc)

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait(10)


def send(reader: Lines, line: str) -> None:
    """One line to a peer's stdin."""
    stdin = reader.proc.stdin
    assert stdin is not None
    stdin.write(line + "\n")
    stdin.flush()
