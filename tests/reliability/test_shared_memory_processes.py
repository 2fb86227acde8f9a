"""Shared memory between Python processes: another OS user, the tools, a hung server.

`cast serve` (shared memory on, as configured by default) and writer and reader processes
(components/shm_peer.py). A client of another OS user gets the same values as bytes and cannot open
the server's memory; `cast record`, `cast replay`, `cast stats` and `cast ls` work with values in
shared memory. kill -9 of writers, readers and the server, and a reader in another network
namespace, are tested in every language in tests/interop/test_shared_memory_interop.py.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from google.protobuf.wrappers_pb2 import BytesValue

from cast.core.records import Identity
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import inspection_pb2_grpc as insp_grpc
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.v1 import working_memory_pb2_grpc as wm_grpc
from cast.wire import shared_memory as wire
from tests.conftest import PYTHONPATH, ServerHandle, wait_for
from tests.netns import Lines
from tests.reliability.conftest import kill9, serve, write_config

COMPONENTS = Path(__file__).resolve().parent / "components"
PEER = str(COMPONENTS / "shm_peer.py")
CONFIG = {"system": "shm", "subarchitectures": {"vision": {}}}


def shared(handle: ServerHandle) -> dict[str, Any]:
    """The server's shared-memory figures (what `cast stats` shows)."""
    with grpc.insecure_channel(handle.endpoint) as channel:
        pb = insp_grpc.InspectionStub(channel).GetMetrics(
            insp_pb2.GetMetricsRequest(), metadata=(("authorization", f"Bearer {handle.token('t', 'vision')}"),),
            timeout=10).shared_memory
    return {f.name: getattr(pb, f.name) for f in pb.DESCRIPTOR.fields}


class Peers:
    """Writer and reader processes of one test, ended at its end."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen[str]] = []

    def start(self, handle: ServerHandle, cid: str, *args: str, prefix: tuple[str, ...] = (),
              env: dict[str, str] | None = None) -> Lines:
        proc = subprocess.Popen([*prefix, sys.executable, PEER, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env={**handle.env(cid, "vision"), **(env or {})})
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


def got(reader: Lines) -> list[tuple[int, int]]:
    """(frame, shared) of each value a reader printed."""
    return [(int(x.split()[2]), int(x.split()[3])) for x in reader.lines if x.startswith("GOT")]


def test_a_client_of_another_os_user_gets_bytes_and_cannot_open_the_servers_memory(
    tmp_path: Path, peers: Peers
) -> None:
    config = write_config(tmp_path / "system.yaml", CONFIG)
    server = serve(config, cwd=tmp_path)
    try:
        # uid 65534 (nobody); it may read this machine's files only so that it can run the same Python.
        other = ("setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "--inh-caps=+dac_read_search",
                 "--ambient-caps=+dac_read_search")
        stranger = peers.start(server, "stranger", "read", prefix=other)
        stranger.wait("WATCHING")
        local = peers.start(server, "local", "read")
        local.wait("WATCHING")
        writer = peers.start(server, "writer", "write", "2")
        writer.wait("DONE")
        wait_for(lambda: got(stranger) == [(0, 0), (1, 0)] and got(local) == [(0, 1), (1, 1)],
                 what="the same values: by shared memory to the server's user, as bytes to the other")
        assert any("this one as 65534" in line for line in stranger.lines), stranger.lines  # its own check
        # The server's check, met by a client that skips its own: HELLO with a valid token is refused.
        with grpc.insecure_channel(server.endpoint) as channel:
            info = dir_grpc.DirectoryStub(channel).DescribeSystem(
                dir_pb2.DescribeSystemRequest(), metadata=(("authorization", f"Bearer {server.token('t', 'vision')}"),),
                timeout=10).shared_memory
        hello = (f"import socket; from cast.wire import shared_memory as w; s = socket.socket(socket.AF_UNIX); "
                 f"s.connect('\\0{info.socket}'); w.send(s, w.hello({server.token('stranger', 'vision')!r})); "
                 "print(w.FrameReader().feed(*w.receive(s)))")
        refused = subprocess.run([*other, sys.executable, "-c", hello], capture_output=True, text=True, timeout=60,
                                 env={**os.environ, "PYTHONPATH": PYTHONPATH})
        assert f"kind={wire.REFUSED}" in refused.stdout and "server's own OS user only" in refused.stdout, refused
        memfds = [f"/proc/{server.process.pid}/fd/{fd}" for fd in os.listdir(f"/proc/{server.process.pid}/fd")
                  if os.readlink(f"/proc/{server.process.pid}/fd/{fd}").startswith("/memfd:cast-arena")]
        assert memfds
        probe = subprocess.run([*other, sys.executable, "-c", f"open({memfds[0]!r}, 'rb')"], capture_output=True,
                               text=True, timeout=60)
        assert probe.returncode != 0 and "PermissionError" in probe.stderr, probe.stderr
    finally:
        server.stop()


def test_record_replay_and_the_tools_with_values_in_shared_memory(tmp_path: Path, peers: Peers) -> None:
    from tests.recording.conftest import cast, read_indexed, record

    config = write_config(tmp_path / "system.yaml", CONFIG)
    server = serve(config, cwd=tmp_path)
    plain = serve(config, cwd=tmp_path, extra=("--no-shared-memory",))
    try:
        recorder = record(server.endpoint, tmp_path / "rec.mcap")
        reader = peers.start(server, "reader", "read")
        reader.wait("WATCHING")
        peers.start(server, "writer", "write", "3").wait("DONE")
        wait_for(lambda: got(reader) == [(k, 1) for k in range(3)], what="three values by shared memory")
        assert any("lent" in line for line in cast("stats", "--endpoint", server.endpoint).stdout.splitlines())
        listing = cast("ls", "--endpoint", server.endpoint).stdout
        assert "in shared memory" in listing, listing
        assert recorder.stop() == 0, recorder.stderr()
        # The recorder, on the host, was lent the values; the file holds their bytes, unchanged.
        values = read_indexed(tmp_path / "rec.mcap").on("/vision/google.protobuf.BytesValue")
        sys.path.insert(0, str(COMPONENTS))
        from shm_peer import frame

        assert [BytesValue.FromString(m.data).value for m in values] == [frame(k) for k in range(3)]
        # Replayed into a server with shared memory off: the same bytes, and that server offers none.
        out = cast("replay", str(tmp_path / "rec.mcap"), "--endpoint", plain.endpoint, "--rate", "max")
        assert out.returncode == 0, out.stderr
        with grpc.insecure_channel(plain.endpoint) as channel:
            meta = (("authorization", f"Bearer {plain.token('t', 'vision')}"),)
            desc = dir_grpc.DirectoryStub(channel).DescribeSystem(dir_pb2.DescribeSystemRequest(), metadata=meta)
            entry = wm_grpc.WorkingMemoryStub(channel).Get(
                wm_pb2.GetRequest(address={"id": "img", "subarchitecture": "vision"}), metadata=meta).entry
        assert not desc.HasField("shared_memory")
        assert BytesValue.FromString(entry.value.value).value == frame(2)
    finally:
        server.stop()
        plain.stop()


def test_a_call_that_opens_the_session_on_a_hung_server_ends_by_its_deadline(tmp_path: Path) -> None:
    """The session is opened on the way of the first read or large write: that opening spends the call's time.

    The first add also registers its type first (one more call on the hung server); a write of a
    registered type that opens the session is in tests/interop/test_shared_memory_interop.py.
    """
    from cast import UnmanagedComponent
    from cast.client.grpc_transport import GrpcTransport
    from cast.errors import DeadlineExceededError

    timeout, margin = 2.0, 1.5  # the call timeout; what a loaded 2-core machine may add before the call returns
    handle = serve(write_config(tmp_path / "system.yaml", CONFIG))
    clients = {}
    try:
        for name in ("get", "add"):  # a client per call, bound before the stop, with no session yet
            clients[name] = client = UnmanagedComponent()
            client._cast_bind(GrpcTransport(handle.endpoint, handle.token(f"c-{name}", "vision"),
                                            Identity(f"c-{name}", "vision"), call_timeout=timeout))
        os.kill(handle.process.pid, signal.SIGSTOP)
        took: dict[str, float] = {}
        try:
            calls = {"get": lambda: clients["get"].get("frame", BytesValue),
                     "add": lambda: clients["add"].add("frame", BytesValue(value=bytes(1 << 20)))}
            for name, call in calls.items():
                started = time.monotonic()
                with pytest.raises(DeadlineExceededError):
                    call()
                took[name] = time.monotonic() - started
        finally:
            os.kill(handle.process.pid, signal.SIGCONT)
        print(f"\ncall timeout {timeout:g} s, the server stopped: "
              + ", ".join(f"{k} {v:.2f} s" for k, v in took.items()))
        assert all(v <= timeout + margin for v in took.values()), took
        # Once the server answers again, the session opens (on a call after the retry pause) and values travel by it.
        clients["add"].add("later", BytesValue(value=bytes(1 << 20)))
        assert wait_for(lambda: isinstance(clients["get"]._transport.get("vision", "later").data, memoryview),
                        timeout=15), "no session with the server after it answered again"
    finally:
        for client in clients.values():
            client._cast_close()
        kill9(handle)
