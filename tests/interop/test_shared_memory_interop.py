"""Large values by shared memory between languages: writers and watchers of each language on one `cast serve`.

The peers (tests/interop/shm_support.py) write and read 1 MiB frames whose every byte tells
which frame it is; a reader reads each value through its view (every byte) and decodes it too,
and says whether it came by shared memory. Every language is a parameter: a language added to
``shm_support.PEERS`` is written to and read by all the others, and its own process tests
(``CLIENTS``: what it cannot write, its fallback, kill -9) run. The rules the server enforces
(forged and stale references, another OS user) are tested in tests/client/test_shared_memory.py
and tests/reliability/test_shared_memory_processes.py, and the Java client's own side of them in
java_client's SharedMemoryTest.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from google.protobuf.wrappers_pb2 import BytesValue

from cast.auth import TokenSigner
from cast.core.records import Identity
from tests.conftest import PYTHONPATH, SECRET, VENV_BIN, wait_for
from tests.interop.shm_support import (
    CLIENTS,
    LANGUAGES,
    Peers,
    checksum,
    dev_shm,
    dev_shm_mapped,
    frame,
    got,
    mappings,
    memory_files,
    same_and_sums,
    shared,
)
from tests.netns import Lines, Namespaces, stop_all
from tests.reliability.conftest import kill9, serve, write_config

CONFIG = {"system": "shm", "subarchitectures": {"vision": {}}}


@pytest.fixture
def peers() -> Iterator[Peers]:
    made = Peers()
    yield made
    made.close()


def bytes_only(reader: Lines, frames: int) -> bool:
    return got(reader) == [(k, 0) for k in range(frames)]


def by_reference(reader: Lines, frames: int) -> bool:
    return got(reader) == [(k, 1) for k in range(frames)]


@pytest.mark.parametrize("writer", LANGUAGES)
def test_values_written_in_one_language_are_read_by_reference_in_every_language(
    tmp_path: Path, peers: Peers, writer: str
) -> None:
    before = dev_shm()
    server = serve(write_config(tmp_path / "system.yaml", CONFIG), cwd=tmp_path)
    try:
        readers = {lang: peers.start(lang, server, f"{lang}-reader", "read") for lang in LANGUAGES}
        for reader in readers.values():
            reader.wait("WATCHING")
        peers.start(writer, server, f"{writer}-writer", "write", "3").wait("DONE")
        sums = [checksum(BytesValue(value=frame(k)).SerializeToString()) for k in range(3)]
        for lang, reader in readers.items():
            wait_for(lambda: by_reference(reader, 3), what=f"three frames by shared memory in {lang}")  # noqa: B023
            if lang in CLIENTS:  # the view read every byte of the value, and the decoded entry has them
                assert same_and_sums(reader) == [(1, s) for s in sums], reader.lines
        stats = shared(server)
        assert stats["staged_writes"] == 3, stats  # the writer staged every frame, none went as bytes
        assert stats["sessions"] == len(LANGUAGES) + 1
        for lang in CLIENTS:  # a read, by getView and get
            assert peers.start(lang, server, f"{lang}-getter", "get").wait("READ").split()[1:] == ["2", "1", "1"]
        # Every process maps the server's segments read-only; only its own staging area is writable.
        for proc in peers.procs:
            maps = mappings(proc.pid)
            assert all(perms[:2] == "r-" and perms[3] == "s" for perms in maps.get("arena", [])), maps
            assert all(perms.startswith("rw") for perms in maps.get("staging", [])), maps
        assert all(mappings(reader.proc.pid).get("arena") for reader in readers.values())
        assert not [dev_shm_mapped(pid) for pid in (server.process.pid, *(p.pid for p in peers.procs))
                    if dev_shm_mapped(pid)]
        for proc in peers.procs:
            assert proc.stdin is not None
            proc.stdin.close()
        for proc in peers.procs:
            assert proc.wait(30) == 0
        wait_for(lambda: shared(server)["sessions"] == 0 and shared(server)["lent_bytes"] == 0,
                 what="every session ended and every value given back")
        assert dev_shm() == before
    finally:
        server.stop()


@pytest.mark.parametrize("language", CLIENTS)
def test_a_reader_cannot_write_the_memory_it_was_lent(tmp_path: Path, peers: Peers, language: str) -> None:
    server = serve(write_config(tmp_path / "system.yaml", CONFIG), cwd=tmp_path)
    try:
        bold = peers.start(language, server, "bold", "read", "trywrite")
        witness = peers.start("python", server, "witness", "read")
        bold.wait("WATCHING")
        witness.wait("WATCHING")
        peers.start(language, server, "writer", "write", "1").wait("DONE")
        attempt = bold.wait("WRITE").split()[1:]
        results = dict(part.split("=", 1) for part in attempt)
        assert "allowed" not in " ".join(attempt), attempt
        assert results["pwrite"] == "EPERM" and results["mmap"] == "EPERM", attempt  # sealed, even by its path
        assert bold.wait("AFTER").split()[1] == "0"  # still frame 0
        wait_for(lambda: got(witness) == [(0, 1)], what="the witness's value, unchanged")
    finally:
        server.stop()


@pytest.mark.parametrize("language", CLIENTS)
def test_a_process_told_not_to_use_shared_memory_writes_and_reads_identical_values_as_bytes(
    tmp_path: Path, peers: Peers, language: str
) -> None:
    server = serve(write_config(tmp_path / "system.yaml", CONFIG), cwd=tmp_path)
    try:
        off = {"CAST_SHARED_MEMORY": "off"}
        plain = peers.start(language, server, "plain-reader", "read", env=off)
        near = peers.start(language, server, "near-reader", "read")
        plain.wait("WATCHING")
        near.wait("WATCHING")
        writer = peers.start(language, server, "plain-writer", "write", "2", env=off)
        writer.wait("DONE")
        wait_for(lambda: bytes_only(plain, 2), what="two frames as bytes to the reader told not to use it")
        # A value written as bytes is still kept in shared memory by the server, and lent on its host.
        wait_for(lambda: by_reference(near, 2), what="the same frames by shared memory to the other reader")
        assert shared(server)["staged_writes"] == 0
        for proc in (plain, writer):
            said = [x for x in proc.lines if "is not used" in x]
            assert len(said) == 1 and "turned off by CAST_SHARED_MEMORY=off" in said[0], proc.lines
    finally:
        server.stop()


@pytest.mark.parametrize("language", CLIENTS)
def test_kill_9_of_a_writer_a_reader_or_the_server_leaves_nothing_behind(
    tmp_path: Path, peers: Peers, language: str
) -> None:
    before = dev_shm()
    server = serve(write_config(tmp_path / "system.yaml", CONFIG), cwd=tmp_path)
    try:
        holder = peers.start(language, server, "holder", "read", "hold")
        holder.wait("WATCHING")
        writer = peers.start(language, server, "writer", "write", "3")
        writer.wait("DONE")
        wait_for(lambda: by_reference(holder, 3), what="three frames held by shared memory")
        assert shared(server)["lent_bytes"] >= 3 * (1 << 20) - 1024  # the holder's views
        os.kill(holder.proc.pid, signal.SIGKILL)
        wait_for(lambda: shared(server)["lent_bytes"] == 0 and shared(server)["sessions"] == 1,
                 what="the killed reader's values given back")
        os.kill(writer.proc.pid, signal.SIGKILL)
        wait_for(lambda: shared(server)["sessions"] == 0, what="the killed writer's session ended")
        assert dev_shm() == before

        reader = peers.start(language, server, "reader", "read")
        reader.wait("WATCHING")
        writer = peers.start(language, server, "writer2", "write", "2")
        writer.wait("DONE")
        wait_for(lambda: by_reference(reader, 2), what="two frames by shared memory")
        assert memory_files(reader.proc.pid) and memory_files(writer.proc.pid)
        kill9(server)
        # Their sessions ended with it: they unmap what they mapped of it (the reader holds no value).
        wait_for(lambda: not memory_files(reader.proc.pid) and not memory_files(writer.proc.pid),
                 what="the dead server's memory unmapped by the live processes")
    finally:
        kill9(server)
    assert dev_shm() == before


@pytest.mark.parametrize("language", CLIENTS)
def test_a_reader_in_another_network_namespace_gets_every_value_as_bytes(
    tmp_path: Path, peers: Peers, language: str
) -> None:
    spaces = Namespaces(second_octet=217)
    procs: list[subprocess.Popen[str]] = []
    try:
        srv_ns, far_ns = spaces.add("shmj"), spaces.add("farj")
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

        def contract(cid: str) -> dict[str, str]:
            return dict(env, CAST_ENDPOINT=endpoint, CAST_COMPONENT_ID=cid, CAST_SUBARCHITECTURE="vision",
                        CAST_TOKEN=signer.issue(Identity(cid, "vision")), CAST_ARGS=json.dumps({}))

        # The peers get their launch contract whole: the server is in a namespace.
        far = peers.start(language, None, "far", "read", prefix=Namespaces.exec(far_ns), base_env=contract("far"))
        near = peers.start(language, None, "near", "read", prefix=Namespaces.exec(srv_ns), base_env=contract("near"))
        far.wait("WATCHING")
        near.wait("WATCHING")
        peers.start(language, None, "writer", "write", "2", prefix=Namespaces.exec(srv_ns),
                    base_env=contract("writer")).wait("DONE")
        wait_for(lambda: bytes_only(far, 2) and by_reference(near, 2),
                 what="every value: as bytes across the namespaces, by shared memory beside the server")
        said = [line for line in far.lines if "is not used" in line]
        assert len(said) == 1 and "not reachable from here" in said[0], far.lines
    finally:
        peers.close()
        stop_all(procs)
        spaces.close()
