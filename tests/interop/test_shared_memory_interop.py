"""Large values by shared memory across languages: writers and readers in Python, C++ and Java on one `cast serve`.

The peers (tests/interop/shm_support.py) write and read 1 MiB frames whose every byte tells which frame
it is; a reader reads each value through its view (every byte: a checksum) and decodes it too, and says
whether it came by shared memory. Every language is a parameter: a language added to
``shm_support.PEERS`` is written to and read by all the others, tries to write what it was lent, and
has its calls that open a session on a hung server end by their deadline, is killed with -9 as
writer, reader and beside a killed server, and reads from another network namespace. The rules the
server enforces (forged and stale references, another OS user) are tested in tests/client/test_shared_memory.py and
tests/reliability/test_shared_memory_processes.py, and each library's own side of them in its unit
tests (C++ cpp_client/tests/server/shared_memory_test.cc, Java SharedMemoryTest).

About 85 s in all on 2 cores shared with other work (most of it starting JVMs), each test 3 to 10 s.
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
    LANGUAGES,
    Peers,
    checksum,
    dev_shm_mapped,
    frame,
    got,
    mappings,
    memory_files,
    same_and_sums,
    send,
    shared,
)
from tests.netns import Lines, Namespaces, stop_all
from tests.reliability.conftest import dev_shm, kill9, serve, write_config

CONFIG = {"system": "shm", "subarchitectures": {"vision": {}}}


@pytest.fixture
def peers() -> Iterator[Peers]:
    made = Peers()
    yield made
    made.close()


def bytes_only(reader: Lines, frames: int, times: int = 1) -> bool:
    return got(reader) == [(k, 0) for k in range(frames)] * times


def by_reference(reader: Lines, frames: int, times: int = 1) -> bool:
    return got(reader) == [(k, 1) for k in range(frames)] * times


def sums(frames: int) -> list[int]:
    """The checksums of the serialised values of frames 0 to ``frames`` - 1, as the readers compute them."""
    return [checksum(BytesValue(value=frame(k)).SerializeToString()) for k in range(frames)]


@pytest.mark.parametrize("made", ["message", "loan"])
@pytest.mark.parametrize("writer", LANGUAGES)
def test_values_written_in_one_language_are_read_by_reference_in_every_language_and_cannot_be_changed(
    tmp_path: Path, peers: Peers, writer: str, made: str
) -> None:
    """Each value the writer wrote (as a message, or made in a loan) reaches every reader by shared memory, identical;
    after each acknowledgement the writer writes 0xFF over its whole staging area, and no reader ever sees a changed
    byte."""
    before = dev_shm()
    server = serve(write_config(tmp_path / "system.yaml", CONFIG), cwd=tmp_path)
    try:
        readers = {lang: peers.start(lang, server, f"{lang}-reader", "read") for lang in LANGUAGES}
        for reader in readers.values():
            reader.wait("WATCHING")
        loan = ("loan",) if made == "loan" else ()
        author = peers.start(writer, server, f"{writer}-writer", "write", "3", "change", *loan)
        author.wait("DONE")
        changed = [int(x.split()[2]) for x in author.lines if x.startswith("CHANGED")]
        assert len(changed) == 3 and all(changed), author.lines  # it had a staging area, and wrote all of it over
        for lang, reader in readers.items():
            wait_for(lambda: by_reference(reader, 3), what=f"three frames by shared memory in {lang}")  # noqa: B023
            # The view read every byte of the value as it was written, and the decoded entry has them.
            assert same_and_sums(reader) == [(1, s) for s in sums(3)], (lang, reader.lines)
        stats = shared(server)
        assert stats["staged_writes"] == 3, stats  # the writer staged every frame, none went as bytes
        assert stats["sessions"] == len(LANGUAGES) + 1
        for lang in LANGUAGES:  # a read after the writer changed its staging area: by getView and get
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


# The ways each language's reader tries to write what it was lent (the peers' WRITE line), and how each must be
# refused: the seals refuse writes through the memory file with EPERM, a write through the view in a child is
# stopped by the kernel (SIGSEGV); None: any refusal.
WAYS: dict[str, dict[str, str | None]] = {
    "python": {"buffer": "TypeError", "pwrite": "EPERM", "mmap": "EPERM"},
    "cpp": {"mprotect": None, "pwrite": "EPERM", "mmap": "EPERM", "child": "SIGSEGV"},
    "java": {"buffer": "ReadOnlyBufferException", "pwrite": "EPERM", "mmap": "EPERM"},
}


@pytest.mark.parametrize("language", LANGUAGES)
def test_a_reader_cannot_write_the_memory_it_was_lent(tmp_path: Path, peers: Peers, language: str) -> None:
    """Through its view, by making its mapping writable, through the memory file opened again read-write by its
    path, through a child writing via the view: every way is refused, and the value stays as it was."""
    server = serve(write_config(tmp_path / "system.yaml", CONFIG), cwd=tmp_path)
    try:
        bold = peers.start(language, server, "bold", "read", "trywrite")
        witness = peers.start("python", server, "witness", "read")
        bold.wait("WATCHING")
        witness.wait("WATCHING")
        peers.start(language, server, "writer", "write", "1").wait("DONE")
        attempt = bold.wait("WRITE").split()[1:]
        refused = dict(part.split("=", 1) for part in attempt)
        assert set(refused) == set(WAYS[language]) and "allowed" not in " ".join(attempt), attempt
        assert all(how in (None, refused[way]) for way, how in WAYS[language].items()), attempt
        assert bold.wait("AFTER").split()[1] == "0"  # still frame 0
        wait_for(lambda: got(witness) == [(0, 1)], what="the witness's value, unchanged")
        assert same_and_sums(witness) == [(1, sums(1)[0])]
    finally:
        server.stop()


def test_processes_told_not_to_use_shared_memory_write_and_read_identical_values_as_bytes(
    tmp_path: Path, peers: Peers
) -> None:
    """``CAST_SHARED_MEMORY=off``: a writer in each language in turn, readers in each, all as bytes, said once;
    a reader beside them is lent the same values."""
    server = serve(write_config(tmp_path / "system.yaml", CONFIG), cwd=tmp_path)
    try:
        off = {"CAST_SHARED_MEMORY": "off"}
        plain = {lang: peers.start(lang, server, f"plain-{lang}", "read", env=off) for lang in LANGUAGES}
        near = peers.start("cpp", server, "near", "read")
        for reader in (*plain.values(), near):
            reader.wait("WATCHING")
        writers = []
        for lang in LANGUAGES:  # one after the other: every reader sees frames 0, 1 from each
            writers.append(peers.start(lang, server, f"plain-writer-{lang}", "write", "2", env=off))
            writers[-1].wait("DONE")
        runs = len(LANGUAGES)
        for lang in LANGUAGES:
            wait_for(lambda: bytes_only(plain[lang], 2, runs),  # noqa: B023
                     what=f"every frame as bytes to the {lang} reader told not to use it")
            assert same_and_sums(plain[lang]) == [(1, s) for s in sums(2)] * runs, plain[lang].lines
        # A value written as bytes is still kept in shared memory by the server, and lent on its host.
        wait_for(lambda: by_reference(near, 2, runs), what="the same frames by shared memory to the other reader")
        assert same_and_sums(near) == [(1, s) for s in sums(2)] * runs, near.lines
        assert shared(server)["staged_writes"] == 0
        for proc in (*plain.values(), *writers):
            said = [x for x in proc.lines if "is not used" in x]
            assert len(said) == 1 and "turned off by CAST_SHARED_MEMORY=off" in said[0], proc.lines
    finally:
        server.stop()


@pytest.mark.parametrize("language", LANGUAGES)
def test_kill_9_of_a_writer_a_reader_or_the_server_leaves_nothing_behind(
    tmp_path: Path, peers: Peers, language: str
) -> None:
    before = dev_shm()
    config = write_config(tmp_path / "system.yaml", CONFIG)
    server = serve(config, cwd=tmp_path)
    try:
        holder = peers.start(language, server, "holder", "read", "hold")
        holder.wait("WATCHING")
        writer = peers.start(language, server, "writer", "write", "3")
        writer.wait("DONE")
        wait_for(lambda: by_reference(holder, 3), what="three frames held by shared memory")
        figures = shared(server)
        assert figures["sessions"] == 2 and figures["lent_bytes"] >= 3 * (1 << 20) - 1024, figures  # the views
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
        assert dev_shm() == before

        # A server started again in the same place: nothing of the dead one to clean, values by shared memory again.
        server = serve(config, cwd=tmp_path)
        again = peers.start(language, server, "again", "read")
        again.wait("WATCHING")
        peers.start(language, server, "writer3", "write", "2").wait("DONE")
        wait_for(lambda: by_reference(again, 2), what="values by shared memory from the new server")
    finally:
        kill9(server)
    assert dev_shm() == before


def test_a_reader_in_another_network_namespace_gets_every_value_as_bytes(tmp_path: Path, peers: Peers) -> None:
    spaces = Namespaces(second_octet=217)
    procs: list[subprocess.Popen[str]] = []
    try:
        srv_ns, far_ns = spaces.add("shmi"), spaces.add("fari")
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

        def start(lang: str, ns: str, cid: str, *args: str) -> Lines:
            # The peers get their launch contract whole: the server is in a namespace.
            contract = dict(env, CAST_ENDPOINT=endpoint, CAST_COMPONENT_ID=cid, CAST_SUBARCHITECTURE="vision",
                            CAST_TOKEN=signer.issue(Identity(cid, "vision")), CAST_ARGS=json.dumps({}))
            return peers.start(lang, None, cid, *args, prefix=Namespaces.exec(ns), base_env=contract)

        far = {lang: start(lang, far_ns, f"far-{lang}", "read") for lang in LANGUAGES}
        near = {lang: start(lang, srv_ns, f"near-{lang}", "read") for lang in LANGUAGES}
        for reader in (*far.values(), *near.values()):
            reader.wait("WATCHING")
        start(LANGUAGES[-1], srv_ns, "writer", "write", "2").wait("DONE")
        for lang in LANGUAGES:
            wait_for(lambda: bytes_only(far[lang], 2) and by_reference(near[lang], 2),  # noqa: B023
                     what=f"every value to {lang}: as bytes across the namespaces, by shared memory beside the server")
            said = [line for line in far[lang].lines if "is not used" in line]
            assert len(said) == 1 and "not reachable from here" in said[0], far[lang].lines
    finally:
        peers.close()
        stop_all(procs)
        spaces.close()


CALL_TIMEOUT_MS = 3000
MARGIN_S = 1.5  # what a loaded 2-core machine may add to a deadline before the call returns (test_hung_server.py)


def test_a_call_that_opens_the_session_on_a_hung_server_ends_by_its_deadline(tmp_path: Path, peers: Peers) -> None:
    """A get and a 1 MiB add on fresh connections in every language, their SA on a server stopped with SIGSTOP
    before it was asked for a session: each ends with DeadlineExceededError by the call timeout (+ the margin),
    the session's opening (DescribeSystem, the handshake) spent from it, not added to it.

    The SA is on a second server: the C++ library opens the session with the directory's server when it
    connects, the others' on the way of the first call that needs them.
    """
    config = write_config(tmp_path / "system.yaml", {
        "system": "shm-deadline", "subarchitectures": {"vision": {}, "motor": {}},
        "servers": {"main": {"subarchitectures": ["vision"]}, "far": {"subarchitectures": ["motor"]}},
    })
    far = serve(config, cwd=tmp_path, extra=("--server", "far"))
    main = serve(config, cwd=tmp_path, extra=("--server", "main", "--route", f"motor={far.endpoint}"))
    try:
        env = {k: v for k, v in os.environ.items() if k not in ("CAST_TOKEN", "CAST_TOKEN_FILE", "CAST_RUNTIME_DIR")}
        env.update(CAST_ENDPOINT=main.endpoint, CAST_SECRET=SECRET, PYTHONPATH=PYTHONPATH,
                   CAST_SUBARCHITECTURE="vision")
        callers = {lang: peers.start(lang, None, lang, "deadline", "motor", str(CALL_TIMEOUT_MS),
                                     base_env=dict(env, CAST_COMPONENT_ID=f"late-{lang}")) for lang in LANGUAGES}
        for caller in callers.values():
            caller.wait("READY")
        os.kill(far.process.pid, signal.SIGSTOP)
        try:
            for caller in callers.values():
                send(caller, "go")
            for caller in callers.values():
                caller.wait("CALLED", timeout=30)
        finally:
            os.kill(far.process.pid, signal.SIGCONT)
        took = {(lang, line.split()[1]): (line.split()[2], int(line.split()[3]) / 1000)
                for lang, caller in callers.items() for line in caller.lines if line.startswith("CALL ")}
        print(f"\ncall timeout {CALL_TIMEOUT_MS / 1000:g} s, the SA's server stopped: "
              + ", ".join(f"{lang} {call} {error} {s:.2f} s" for (lang, call), (error, s) in took.items()))
        assert set(took) == {(lang, call) for lang in LANGUAGES for call in ("get", "add")}, took
        for (lang, call), (error, seconds) in took.items():
            assert error == "DeadlineExceededError", (lang, call, callers[lang].lines)
            assert seconds <= CALL_TIMEOUT_MS / 1000 + MARGIN_S, (lang, call, seconds)
    finally:
        peers.close()
        main.stop()
        kill9(far)
