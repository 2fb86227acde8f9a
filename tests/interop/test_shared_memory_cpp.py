"""Large values by shared memory with the C++ client and across languages, over a real `cast serve`
(docs/client-protocol.md, "Large values by shared memory").

Writers and readers are processes of their own that print the same lines in every language:
tests/reliability/components/shm_peer.py (Python) and cast_test_shm (C++,
cpp_client/tests/components/cast_test_shm.cc). A language is one entry of :data:`LANGUAGES` and one branch of
:func:`peer_command`; the tests run over every entry (Python's own process tests are
tests/reliability/test_shared_memory_processes.py). Checked: the values every reader gets are identical to what was
written and came by shared memory (the server's figures say the writer staged them); a view reads the same bytes as
the decoded entry; a C++ reader cannot write the memory it was lent; ``CAST_SHARED_MEMORY=off`` and another network
namespace give the same values as bytes, said once at INFO; kill -9 of a C++ writer or reader gives back what it held
and leaves nothing in ``/dev/shm``, and a dead server's memory is unmapped by the C++ processes that had it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
import yaml
from google.protobuf.wrappers_pb2 import BytesValue

from cast.auth import TokenSigner
from cast.core.records import Identity
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import inspection_pb2_grpc as insp_grpc
from tests.conftest import PYTHONPATH, SECRET, VENV_BIN, ServerHandle, start_server, wait_for
from tests.interop.cpp_support import cpp_executable
from tests.netns import Lines, Namespaces, stop_all

PEER_PY = Path(__file__).resolve().parents[1] / "reliability" / "components" / "shm_peer.py"
CONFIG = {"system": "shm-interop", "subarchitectures": {"vision": {}}}
LANGUAGES = ("python", "cpp")  # the Java helper adds "java" here and in peer_command()
NATIVE = tuple(lang for lang in LANGUAGES if lang != "python")  # clients whose own process tests live here
SIZE = 1 << 20


def peer_command(lang: str, *args: str) -> list[str]:
    """The command of a writer or reader process in ``lang``."""
    if lang == "python":
        return [sys.executable, str(PEER_PY), *args]
    if lang == "cpp":
        return [str(cpp_executable("cast_test_shm")), *args]
    raise AssertionError(f"no shared-memory peer for {lang}")


def frame(k: int) -> bytes:
    """Frame ``k`` as the peers write it (shm_peer.py's frame())."""
    return bytes((k * 7 + i) % 253 for i in range(253)) * (SIZE // 253)


def checksum(data: bytes) -> int:
    """The checksum cast_test_shm computes over a view's bytes."""
    total = 0
    for b in data:
        total = (total * 31 + b) & 0xFFFFFFFFFFFFFFFF
    return total


class Peers:
    """Writer and reader processes of one test, killed at its end."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen[str]] = []

    def start(self, lang: str, env: dict[str, str], *args: str, prefix: tuple[str, ...] = ()) -> Lines:
        proc = subprocess.Popen([*prefix, *peer_command(lang, *args)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env)
        self.procs.append(proc)
        return Lines(proc)

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait(10)


@pytest.fixture
def peers() -> Iterator[Peers]:
    made = Peers()
    yield made
    made.close()


@pytest.fixture
def shm_server(tmp_path: Path) -> Iterator[ServerHandle]:
    handle = start_server(tmp_path, CONFIG)
    yield handle
    handle.stop()


def got(reader: Lines) -> list[list[int]]:
    """The fields after GOT of each value a reader printed: revision, frame, shared (and same, sum from C++)."""
    return [[int(x) for x in line.split()[1:]] for line in reader.lines if line.startswith("GOT")]


def frames_of(reader: Lines) -> list[tuple[int, int]]:
    """(frame, shared) of each value a reader printed."""
    return [(g[1], g[2]) for g in got(reader)]


def has_got(reader: Lines, count: int) -> Callable[[], bool]:
    """Whether ``reader`` printed ``count`` values, as a condition to wait for."""
    return lambda: len(got(reader)) == count


def frames_are(reader: Lines, expected: list[tuple[int, int]]) -> Callable[[], bool]:
    """Whether ``reader`` printed these (frame, shared), as a condition to wait for."""
    return lambda: frames_of(reader) == expected


def shared(handle: ServerHandle) -> dict[str, Any]:
    """The server's shared-memory figures (what `cast stats` shows)."""
    with grpc.insecure_channel(handle.endpoint) as channel:
        pb = insp_grpc.InspectionStub(channel).GetMetrics(
            insp_pb2.GetMetricsRequest(), metadata=(("authorization", f"Bearer {handle.token('t', 'vision')}"),),
            timeout=10).shared_memory
    return {f.name: getattr(pb, f.name) for f in pb.DESCRIPTOR.fields}


def memory_files(pid: int) -> list[str]:
    """The server memory files a process maps."""
    with open(f"/proc/{pid}/maps") as maps:
        return [line for line in maps if "memfd:cast-" in line]


def said_once(lines: list[str], text: str) -> bool:
    """Whether exactly one line says ``text``."""
    return sum(text in line for line in lines) == 1


@pytest.mark.parametrize("writer_lang", LANGUAGES)
def test_values_by_shared_memory_are_identical_in_every_language(
    shm_server: ServerHandle, peers: Peers, writer_lang: str
) -> None:
    readers = {lang: peers.start(lang, shm_server.env(f"reader-{lang}", "vision"), "read") for lang in LANGUAGES}
    for reader in readers.values():
        reader.wait("WATCHING")
    before = shared(shm_server)
    writer = peers.start(writer_lang, shm_server.env(f"writer-{writer_lang}", "vision"), "write", "3")
    writer.wait("DONE")
    for lang, reader in readers.items():
        wait_for(has_got(reader, 3), what=f"three values to the {lang} reader")
        assert frames_of(reader) == [(k, 1) for k in range(3)], (lang, reader.lines)
        assert not [x for x in reader.lines if x.startswith("MISMATCH")], reader.lines  # view == decoded entry
    for lang in NATIVE:
        # The view read the bytes of the decoded entry, every byte of them (the checksum).
        sums = [checksum(BytesValue(value=frame(k)).SerializeToString()) for k in range(3)]
        assert [(g[3], g[4]) for g in got(readers[lang])] == [(1, s) for s in sums], readers[lang].lines
    after = shared(shm_server)
    assert after["staged_writes"] - before["staged_writes"] == 3  # the writer staged every value
    assert after["lent"] - before["lent"] >= 3 * len(readers)
    for lang in NATIVE:
        getter = peers.start(lang, shm_server.env(f"getter-{lang}", "vision"), "get")
        assert getter.wait("READ").split()[1:] == ["2", "1", "1"], getter.lines
    wait_for(lambda: shared(shm_server)["lent_bytes"] == 0, what="every value given back once not held")


@pytest.mark.parametrize("lang", NATIVE)
def test_a_reader_cannot_write_the_memory_it_was_lent(shm_server: ServerHandle, peers: Peers, lang: str) -> None:
    bold = peers.start(lang, shm_server.env("bold", "vision"), "read", "trywrite")
    witness = peers.start("python", shm_server.env("witness", "vision"), "read")
    bold.wait("WATCHING")
    witness.wait("WATCHING")
    peers.start(lang, shm_server.env("writer", "vision"), "write", "1").wait("DONE")
    # Each language tries what it can (C++: mprotect, pwrite and mmap of the memory file opened again by its
    # path, a child writing through the view), one `name=result` each: none may be allowed.
    attempt = bold.wait("WRITE").split()[1:]
    results = dict(part.split("=", 1) for part in attempt)
    assert results and "allowed" not in " ".join(attempt), attempt
    if lang == "cpp":
        assert set(results) == {"mprotect", "pwrite", "mmap", "child"}, attempt
        assert results["child"] == "SIGSEGV", attempt  # a write through the view itself: the kernel stops it
        assert results["pwrite"] == "EPERM" and results["mmap"] == "EPERM", attempt  # the seal, through a path too
    assert bold.wait("AFTER").split()[1] == "0"  # still frame 0
    wait_for(lambda: frames_of(witness) == [(0, 1)], what="the witness's value")


@pytest.mark.parametrize("writer_lang", LANGUAGES)
def test_shared_memory_turned_off_gives_identical_values_as_bytes(
    shm_server: ServerHandle, peers: Peers, writer_lang: str
) -> None:
    off = {"CAST_SHARED_MEMORY": "off"}
    readers = {lang: peers.start(lang, {**shm_server.env(f"off-{lang}", "vision"), **off}, "read")
               for lang in LANGUAGES}
    on = peers.start("cpp", shm_server.env("on-cpp", "vision"), "read")
    for reader in (*readers.values(), on):
        reader.wait("WATCHING")
    before = shared(shm_server)
    writer = peers.start(writer_lang, {**shm_server.env("off-writer", "vision"), **off}, "write", "2")
    writer.wait("DONE")
    for lang, reader in readers.items():
        wait_for(has_got(reader, 2), what=f"two values to the {lang} reader")
        assert frames_of(reader) == [(0, 0), (1, 0)], (lang, reader.lines)
    wait_for(lambda: frames_of(on) == [(0, 1), (1, 1)], what="the values by shared memory beside them")
    assert shared(shm_server)["staged_writes"] == before["staged_writes"]  # the writer sent bytes
    text = "is not used (turned off by CAST_SHARED_MEMORY=off): values travel as bytes"
    for proc in (writer, *(readers[lang] for lang in NATIVE)):
        assert said_once(proc.lines, text), proc.lines


def test_a_reader_in_another_network_namespace_gets_every_value_as_bytes(tmp_path: Path) -> None:
    spaces = Namespaces(second_octet=216)
    procs: list[subprocess.Popen[str]] = []
    try:
        srv_ns, far_ns = spaces.add("shmc"), spaces.add("farc")
        srv_ip, _ = spaces.link(srv_ns, far_ns)
        config = tmp_path / "system.yaml"
        config.write_text(yaml.safe_dump(CONFIG))
        env = dict(os.environ, CAST_SECRET=SECRET, PYTHONPATH=PYTHONPATH)
        server = subprocess.Popen([*Namespaces.exec(srv_ns), str(VENV_BIN / "cast"), "serve", str(config),
                                   "--listen", f"{srv_ip}:0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  text=True, env=env, cwd=tmp_path)
        procs.append(server)
        assert server.stdout is not None
        endpoint = server.stdout.readline().strip().removeprefix("listening on ")
        signer = TokenSigner(SECRET.encode())

        def peer(ns: str, lang: str, cid: str, *args: str) -> Lines:
            cenv = dict(env, CAST_ENDPOINT=endpoint, CAST_COMPONENT_ID=cid, CAST_SUBARCHITECTURE="vision",
                        CAST_TOKEN=signer.issue(Identity(cid, "vision")), CAST_ARGS=json.dumps({}))
            proc = subprocess.Popen([*Namespaces.exec(ns), *peer_command(lang, *args)], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=cenv)
            procs.append(proc)
            return Lines(proc)

        far = {lang: peer(far_ns, lang, f"far-{lang}", "read") for lang in NATIVE}
        near = {lang: peer(srv_ns, lang, f"near-{lang}", "read") for lang in NATIVE}
        for reader in (*far.values(), *near.values()):
            reader.wait("WATCHING")
        peer(srv_ns, NATIVE[0], "writer", "write", "3").wait("DONE")
        for lang in NATIVE:
            wait_for(frames_are(far[lang], [(k, 0) for k in range(3)]),
                     what=f"every value to {lang} across the namespaces, as bytes")
            wait_for(frames_are(near[lang], [(k, 1) for k in range(3)]),
                     what=f"every value to {lang} beside the server, by shared memory")
            assert said_once(far[lang].lines, "not reachable from here"), far[lang].lines
    finally:
        stop_all(procs)
        spaces.close()


@pytest.mark.parametrize("lang", NATIVE)
def test_kill_9_of_a_writer_or_reader_returns_what_it_held_and_leaves_nothing_behind(
    shm_server: ServerHandle, peers: Peers, lang: str
) -> None:
    before = set(os.listdir("/dev/shm"))
    holder = peers.start(lang, shm_server.env("holder", "vision"), "read", "hold")
    holder.wait("WATCHING")
    writer = peers.start(lang, shm_server.env("writer", "vision"), "write", "4")
    writer.wait("DONE")
    wait_for(lambda: frames_of(holder) == [(k, 1) for k in range(4)], what="four values by shared memory")
    figures = shared(shm_server)
    assert figures["sessions"] == 2 and figures["lent_bytes"] > 0  # the holder's views
    os.kill(holder.proc.pid, signal.SIGKILL)
    wait_for(lambda: shared(shm_server)["lent_bytes"] == 0 and shared(shm_server)["sessions"] == 1,
             what="the killed reader's values given back")
    os.kill(writer.proc.pid, signal.SIGKILL)
    wait_for(lambda: shared(shm_server)["sessions"] == 0, what="the killed writer's session ended")
    assert set(os.listdir("/dev/shm")) == before

    reader = peers.start(lang, shm_server.env("reader", "vision"), "read")
    reader.wait("WATCHING")
    writer = peers.start(lang, shm_server.env("writer2", "vision"), "write", "2")
    writer.wait("DONE")
    wait_for(lambda: len(got(reader)) == 2, what="two values")
    assert memory_files(reader.proc.pid) and memory_files(writer.proc.pid)
    os.kill(shm_server.process.pid, signal.SIGKILL)
    shm_server.process.wait(10)
    # Their streams to it broke: they unmap what they mapped of it.
    wait_for(lambda: not memory_files(reader.proc.pid) and not memory_files(writer.proc.pid),
             what="the dead server's memory unmapped by the live processes")
    assert set(os.listdir("/dev/shm")) == before
