"""A recording across a server restart and a cut connection: nothing lost when the history covers the outage,
and when it does not, the gap is in the file (/cast/gaps), in `cast info` and on stderr, never silent."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter

import cast
from cast.errors import UnavailableError
from cast.recording.channels import parse_gap
from cast.v1.entry_pb2 import ChangeEvent
from tests.conftest import ServerHandle, wait_for
from tests.recording.conftest import RecordProcess, cli_env, read_indexed, record, wait_recorded
from tests.recording.conftest import cast as cast_cli
from tests.reliability.conftest import kill9, serve, write_config
from tests.reliability.proxy import Proxy


def _write(component: Any, prefix: str, n: int) -> None:
    """Write n entries, retrying while the server is away (an add that answers ALREADY_EXISTS was applied)."""
    for i in range(n):
        while True:
            try:
                component.add(f"{prefix}-{i}", Counter(value=i))
                break
            except UnavailableError:
                time.sleep(0.05)
            except cast.AlreadyExistsError:
                break


def _revisions(path: Path) -> list[int]:
    return [ChangeEvent.FromString(m.data).revision for m in read_indexed(path).on("/cast/changes")]


def test_a_server_restart_during_recording_loses_nothing(tmp_path: Path, recorders: list[RecordProcess]) -> None:
    config = write_config(tmp_path / "system.yaml", {
        "system": "durable", "subarchitectures": {"vision": {}},
        "persistence": {"path": str(tmp_path / "wm.db"), "durability": "batch"}})
    server = serve(config)
    port = server.endpoint.rpartition(":")[2]
    path = tmp_path / "restart.mcap"
    rec = record(server.endpoint, path)
    recorders.append(rec)
    writer = server.connect("w", "vision")
    try:
        _write(writer, "before", 20)
        wait_recorded(path, 20)
        kill9(server)
        server = serve(config, listen=f"127.0.0.1:{port}")  # the same port: the recorder reconnects by itself
        _write(writer, "after", 20)
        wait_recorded(path, 40)
        assert rec.stop(signal.SIGINT) == 0, rec.stderr()
    finally:
        writer._cast_close()
        server.stop()
    assert _revisions(path) == list(range(1, 41))  # every change once, in order, across the restart
    assert "/cast/gaps" not in read_indexed(path).topics() and "gap" not in rec.stderr()


def test_an_outage_longer_than_the_history_is_a_marked_gap(
    server_factory: Any, tmp_path: Path, recorders: list[RecordProcess]
) -> None:
    server: ServerHandle = server_factory({"system": "small", "subarchitectures": {"vision": {}},
                                           "limits": {"history_events": 10}})
    proxy = Proxy(server.endpoint)
    path = tmp_path / "gap.mcap"
    # All its traffic through the proxy, as a recorder on another host has: on the server's host its events would
    # come on a shared-memory session's socket, which the proxy does not carry, and the server could send it the
    # first write after the cut there before it noticed the cut gRPC call (revision 6 recorded, the gap 7..35).
    rec = record(proxy.endpoint, path, env=cli_env(CAST_SHARED_MEMORY="off"))
    recorders.append(rec)
    writer = server.connect("w", "vision")  # directly, not through the proxy
    try:
        _write(writer, "seen", 5)
        wait_recorded(path, 5)
        proxy.cut()  # the recorder's connection breaks and it cannot come back yet
        _write(writer, "missed", 30)  # revisions 6..35; the server keeps only the last 10
        proxy.restore()
        wait_for(lambda: "gap in" in rec.stderr(), what="the recorder to report the gap")
        _write(writer, "later", 3)  # 36..38
        wait_recorded(path, 5 + 3, what="the changes after the outage")
        assert rec.stop(signal.SIGINT) == 1, rec.stderr()  # 1: the file is complete but not every change is in it
    finally:
        writer._cast_close()
        proxy.close()
    read = read_indexed(path)
    (gap,) = [parse_gap(m.data, m.log_time) for m in read.on("/cast/gaps")]
    assert read.channel("/cast/gaps").metadata == {"cast.role": "gaps"}
    assert _revisions(path) == [1, 2, 3, 4, 5, 36, 37, 38]
    assert (gap.subarchitecture, gap.last_revision, gap.resumed_revision, gap.missing) == ("vision", 5, 36, 30)
    assert "revision 6 is no longer in the history (kept: 26..35)" in gap.reason
    assert "gap in subarchitecture 'vision': revisions 6..35 (30 changes) are not recorded" in rec.stderr()
    assert "1 gap(s)" in rec.stderr()
    info = json.loads(cast_cli("info", str(path), "--json").stdout)
    assert [(g["subarchitecture"], g["last_revision"], g["missing"]) for g in info["gaps"]] == [
        ("vision", 5, gap.missing)]
    table = cast_cli("info", str(path)).stdout
    assert "1 gap(s)" in table and "no longer in the history" in table
    fresh = server_factory({"system": "fresh", "subarchitectures": {"vision": {}}})
    out = cast_cli("replay", str(path), "--endpoint", fresh.endpoint, "--rate", "max")
    assert out.returncode == 0, out.stderr  # what is in the file is replayed, and the gap is said
    assert "the recording has a gap in subarchitecture 'vision': revisions 6..35" in out.stderr
    assert "8 changes written" in out.stderr


def test_a_server_restarted_without_its_history_is_a_marked_gap(
    tmp_path: Path, recorders: list[RecordProcess]
) -> None:
    config = write_config(tmp_path / "system.yaml", {"system": "memory", "subarchitectures": {"vision": {}}})
    server = serve(config)
    port = server.endpoint.rpartition(":")[2]
    path = tmp_path / "lost.mcap"
    rec = record(server.endpoint, path)
    recorders.append(rec)
    writer = server.connect("w", "vision")
    try:
        _write(writer, "old", 3)
        wait_recorded(path, 3)
        kill9(server)
        server = serve(config, listen=f"127.0.0.1:{port}")  # memory only: a new history, revisions from 1 again
        wait_for(lambda: "gap in" in rec.stderr(), what="the recorder to report the gap")
        _write(writer, "new", 4)
        wait_recorded(path, 3 + 4, what="the changes after the restart")
        assert rec.stop(signal.SIGINT) == 1, rec.stderr()
    finally:
        writer._cast_close()
        server.stop()
    read = read_indexed(path)
    (gap,) = [parse_gap(m.data, m.log_time) for m in read.on("/cast/gaps")]
    assert _revisions(path) == [1, 2, 3, 1, 2, 3, 4]  # the new history numbers from 1 again
    assert (gap.last_revision, gap.resumed_revision, gap.missing) == (3, 1, None)
    assert gap.history_before and gap.history_after and gap.history_before != gap.history_after
    assert "restarted without it" in gap.reason
    assert "gap in subarchitecture 'vision': changes after revision 3 of history" in rec.stderr()


def test_a_recorder_that_falls_behind_the_history_marks_the_gap_and_goes_on(
    server_factory: Any, tmp_path: Path, recorders: list[RecordProcess]
) -> None:
    server: ServerHandle = server_factory({"system": "slow", "subarchitectures": {"vision": {}},
                                           "limits": {"history_events": 100}})
    path = tmp_path / "behind.mcap"
    rec = record(server.endpoint, path)
    recorders.append(rec)
    writer = server.connect("w", "vision")
    try:
        writer.add("first", Counter(value=0))
        wait_recorded(path, 1)
        rec.process.send_signal(signal.SIGSTOP)  # the recorder stops reading; its connection stays open
        try:
            blob = "x" * 2000
            for b in range(100):  # 20,000 changes of 2 kB: far more than any socket and HTTP/2 window hold
                writer.batch([("add", f"k{b}-{i}", Counter(writer=blob, value=i)) for i in range(200)])
        finally:
            rec.process.send_signal(signal.SIGCONT)
        wait_for(lambda: "gap in" in rec.stderr(), what="the recorder to report the gap")
        writer.add("last", Counter(value=1))
        wait_for(lambda: any(e.address.id == "last" for e in wait_recorded(path, 2)), what="the change after it")
        assert rec.stop(signal.SIGINT) == 1, rec.stderr()
    finally:
        writer._cast_close()
    read = read_indexed(path)
    (gap,) = [parse_gap(m.data, m.log_time) for m in read.on("/cast/gaps")]
    revisions = _revisions(path)
    assert revisions[-1] == 20_002 and gap.resumed_revision == 20_002
    before = revisions[:-1]
    assert before == list(range(1, len(before) + 1)) and gap.last_revision == len(before)  # nothing out of order
    assert gap.missing == 20_001 - len(before) > 0 and "is no longer in the history" in gap.reason
