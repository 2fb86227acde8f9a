"""Durability: the journal restores every acknowledged write, versions, revisions and schemas.

In process: a System with a journal is written, dropped (a crash) or closed, and
a new System on the same file must hold the same state. Over processes: `cast
serve` is killed with SIGKILL while writers write, restarted, and every write
the writers saw acknowledged must be there (0 lost for `always` and `batch`).
"""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Counter, Pose
from google.protobuf import any_pb2

from cast.core.journal import Journal
from cast.core.records import BatchOp, Identity, Limits, Operation
from cast.core.schemas import files_of
from cast.core.system import TASK_TYPE, System
from cast.core.watch import EventFilter, Subscription
from cast.errors import HistoryExpiredError
from cast.v1 import directory_pb2, directory_pb2_grpc, entry_pb2, working_memory_pb2, working_memory_pb2_grpc
from tests.conftest import PYTHONPATH, SECRET, VENV_BIN
from tests.reliability.conftest import kill9, metadata, serve, wait_for, write_config
from tests.reliability.figures import record, soak
from tests.terminal import Terminal

A = Identity("a", "vision")
B = Identity("b", "language")


def make(path: Path, mode: str, history: int = 64) -> System:
    journal = Journal(path, mode, history)
    return System("t", ["vision", "language"], limits=Limits(history_events=history), journal=journal)


def state(system: System) -> dict[str, Any]:
    host = system.host
    return {
        sa: {
            "revision": host.revision(sa),
            "entries": [(r.id, r.type, r.data, r.version, r.author, r.revision) for r in host.all_entries(sa)],
        }
        for sa in host.subarchitectures
    }


@pytest.mark.parametrize("mode", ["always", "batch", "none"])
def test_clean_restart_keeps_entries_versions_revisions_and_schemas(tmp_path: Path, mode: str) -> None:
    path = tmp_path / "wm.db"
    s = make(path, mode)
    s.schemas.register(files_of(Pose.DESCRIPTOR))
    h = s.host
    h.add(A, "vision", "p", "cast.testing.Pose", Pose(x=1).SerializeToString())
    h.overwrite(A, "vision", "p", "cast.testing.Pose", Pose(x=2).SerializeToString())
    h.add(A, "vision", "gone", "cast.testing.Pose", b"")
    h.overwrite(A, "vision", "gone", "cast.testing.Pose", b"")
    h.delete(A, "vision", "gone")
    h.batch(B, [BatchOp(Operation.ADD, "language", f"l{i}", "cast.testing.Counter", b"") for i in range(3)])
    s.sessions.register(A, "python", "managed", 1, "h")
    task = s.tasks.propose(A, "work")  # live task: its session ends with the server
    s.durable_sync()
    before = state(s)
    history_id = s.history_id
    s.close()

    s2 = make(path, mode)
    after = state(s2)
    # The live task's entry is deleted on restore (one more revision); everything else is identical.
    assert after["language"] == before["language"]
    assert [e for e in after["vision"]["entries"] if e[1] != TASK_TYPE] == [
        e for e in before["vision"]["entries"] if e[1] != TASK_TYPE
    ]
    assert not s2.host.exists(A, "vision", task.task_id)
    assert after["vision"]["revision"] == before["vision"]["revision"] + 1
    assert s2.history_id == history_id
    assert s2.schemas.known("cast.testing.Pose")
    # Counters continue: next revision, next version after delete.
    assert s2.host.add(A, "vision", "gone", "cast.testing.Pose", b"").version == 2
    assert s2.host.overwrite(A, "vision", "p", "cast.testing.Pose", b"").version == 2
    # The history survived: a watcher resumes from revision 1 with every event, in order.
    sub = Subscription(s2.host, lambda: None)
    sub.add_watch(1, [EventFilter(subarchitecture="vision")], {"vision": 1})
    revs = [m.event.revision for m in sub.poll()]
    assert revs == list(range(1, s2.host.revision("vision") + 1))
    s2.close()


@pytest.mark.parametrize("mode", ["always", "batch"])
def test_a_crash_keeps_every_acknowledged_write(tmp_path: Path, mode: str) -> None:
    """A System dropped without close (as by SIGKILL): what durable_sync covered is all there."""
    path = tmp_path / "wm.db"
    s = make(path, mode)
    for i in range(200):
        s.host.add(A, "vision", f"e{i}", "cast.testing.Counter", Counter(value=i).SerializeToString())
        if i % 7 == 0:
            s.host.delete(A, "vision", f"e{i}")
    s.durable_sync()
    before = state(s)
    # No close(): the committer thread is simply abandoned, the clean mark never written.
    s2 = make(path, mode)
    assert state(s2) == before
    assert not s2.journal.was_clean  # type: ignore[union-attr]
    assert s2.history_id == s.history_id  # durable modes keep the history: watchers may resume


def test_a_crash_in_mode_none_starts_a_new_history(tmp_path: Path) -> None:
    path = tmp_path / "wm.db"
    s = make(path, "none")
    s.host.add(A, "vision", "x", "cast.testing.Counter", b"")
    s2 = make(path, "none")  # crashed: acknowledged writes may be missing, so watchers must resynchronise
    assert s2.history_id != s.history_id


def test_history_on_disk_is_bounded_and_a_too_old_resume_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "wm.db"
    s = make(path, "batch", history=16)
    for i in range(3000):
        s.host.add(A, "vision", f"e{i}", "cast.testing.Counter", b"")
    s.close()
    s2 = make(path, "batch", history=16)
    assert s2.host.revision("vision") == 3000
    rows = s2.journal._db.execute("SELECT COUNT(*) FROM events").fetchone()[0]  # type: ignore[union-attr]
    assert rows < 3000  # trimmed to about history_events per WM (plus the trim period)
    sub = Subscription(s2.host, lambda: None)
    with pytest.raises(HistoryExpiredError):
        sub.add_watch(1, [EventFilter()], {"vision": 1})
    sub.add_watch(2, [EventFilter()], {"vision": 2990})
    assert [m.event.revision for m in sub.poll()] == list(range(2990, 3001))
    s2.close()


def test_group_commit_makes_fewer_transactions_than_writes(tmp_path: Path) -> None:
    s = make(tmp_path / "wm.db", "batch")
    done = threading.Barrier(8)

    def writer(k: int) -> None:
        done.wait()
        for i in range(100):
            s.host.add(Identity(f"w{k}", "vision"), "vision", f"w{k}-{i}", "cast.testing.Counter", b"")
            s.durable_sync()

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert s.host.entry_count("vision") == 800
    assert s.journal is not None and s.journal.commits < 800
    record("group_commit", {"writers": 8, "writes": 800, "transactions": s.journal.commits})
    s.close()


# ------------------------------------------------------------------ kill -9 over processes


def _any(value: int) -> any_pb2.Any:
    packed = any_pb2.Any()
    packed.Pack(Counter(value=value))
    return packed


def _kill_under_load(tmp_path: Path, mode: str, writers: int, seconds: float) -> dict[str, Any]:
    db = tmp_path / "wm.db"
    config = write_config(
        tmp_path / "system.yaml",
        {"system": "durable", "subarchitectures": {"vision": {}}, "persistence": {"path": str(db), "durability": mode}},
    )
    handle = serve(config)
    acked: dict[str, int] = {}  # id -> highest acknowledged version
    acked_lock = threading.Lock()
    max_revision = [0]
    stop = threading.Event()

    def writer(k: int) -> None:
        ch = grpc.insecure_channel(handle.endpoint)
        stub = working_memory_pb2_grpc.WorkingMemoryStub(ch)
        md = metadata(handle, f"w{k}", "vision")
        i = 0
        counter = f"w{k}-counter"
        try:
            stub.Add(working_memory_pb2.AddRequest(
                address=entry_pb2.EntryAddress(id=counter, subarchitecture="vision"), value=_any(0)), metadata=md)
            with acked_lock:
                acked[counter] = 0
            while not stop.is_set():
                i += 1
                if i % 2:
                    req: Any = working_memory_pb2.AddRequest(
                        address=entry_pb2.EntryAddress(id=f"w{k}-{i}", subarchitecture="vision"), value=_any(i))
                    resp = stub.Add(req, metadata=md, timeout=10)
                    key = f"w{k}-{i}"
                else:
                    req = working_memory_pb2.OverwriteRequest(
                        address=entry_pb2.EntryAddress(id=counter, subarchitecture="vision"), value=_any(i))
                    resp = stub.Overwrite(req, metadata=md, timeout=10)
                    key = counter
                with acked_lock:  # the writer's own log of acknowledgements
                    acked[key] = max(acked.get(key, -1), resp.version)
                    max_revision[0] = max(max_revision[0], resp.revision)
        except grpc.RpcError:
            pass  # the server died under us: this write was not acknowledged
        finally:
            ch.close()

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(writers)]
    for t in threads:
        t.start()
    wait_for(lambda: len(acked) >= writers * 5, what="writes acknowledged")
    time.sleep(seconds)
    kill9(handle)
    stop.set()
    for t in threads:
        t.join(20)
    with acked_lock:
        log = dict(acked)
        top = max_revision[0]
    handle2 = serve(config)
    try:
        ch = grpc.insecure_channel(handle2.endpoint)
        stub = working_memory_pb2_grpc.WorkingMemoryStub(ch)
        md = metadata(handle2, "checker", "vision")
        lost = []
        for key, version in log.items():
            try:
                got = stub.Get(working_memory_pb2.GetRequest(
                    address=entry_pb2.EntryAddress(id=key, subarchitecture="vision")), metadata=md, timeout=10)
                if got.entry.version < version:
                    lost.append(key)
            except grpc.RpcError as exc:
                assert exc.code() == grpc.StatusCode.NOT_FOUND
                lost.append(key)
        desc = directory_pb2_grpc.DirectoryStub(ch).DescribeSystem(
            directory_pb2.DescribeSystemRequest(), metadata=md, timeout=10)
        revision = desc.subarchitectures[0].revision
        ch.close()
    finally:
        handle2.stop()
    return {"mode": mode, "acknowledged": len(log), "lost": len(lost), "max_acked_revision": top,
            "revision_after_restart": revision, "lost_ids": lost[:5]}


@pytest.mark.parametrize("mode", ["always", "batch", "none"])
def test_kill9_under_write_load_loses_no_acknowledged_write(tmp_path: Path, mode: str) -> None:
    result = _kill_under_load(tmp_path, mode, writers=8 if soak() else 4, seconds=20.0 if soak() else 1.0)
    record(f"kill9_server_{mode}", {k: v for k, v in result.items() if k != "lost_ids"})
    print(json.dumps(result))
    if mode != "none":
        assert result["lost"] == 0, result
        assert result["revision_after_restart"] >= result["max_acked_revision"]


def test_cast_serve_of_one_server_of_several_keeps_its_persistence(tmp_path: Path) -> None:
    """`cast serve --server NAME` serves that server's SAs with its journal; without it, a
    configuration whose servers have persistence is refused rather than served in memory."""
    config = write_config(tmp_path / "two.yaml", {
        "system": "two",
        "subarchitectures": {"vision": {}, "language": {}},
        "servers": {
            "eyes": {"subarchitectures": ["vision"], "persistence": {"path": "eyes.db", "durability": "always"}},
            "words": {"subarchitectures": ["language"]},
        },
    })
    cast_bin = str(VENV_BIN / "cast")
    env = dict(os.environ, CAST_SECRET=SECRET, PYTHONPATH=PYTHONPATH)
    refused = subprocess.run([cast_bin, "serve", str(config), "--listen", "127.0.0.1:0"], env=env,
                             capture_output=True, text=True, timeout=60)
    assert refused.returncode != 0 and "--server" in refused.stderr and "eyes" in refused.stderr, refused.stderr
    unknown = subprocess.run([cast_bin, "serve", str(config), "--server", "ears"], env=env,
                             capture_output=True, text=True, timeout=60)
    assert unknown.returncode != 0 and "eyes, words" in unknown.stderr, unknown.stderr

    value = any_pb2.Any()
    value.Pack(Pose(label="kept"))
    handle = serve(config, extra=("--server", "eyes"))
    try:
        stub = working_memory_pb2_grpc.WorkingMemoryStub(grpc.insecure_channel(handle.endpoint))
        stub.Add(working_memory_pb2.AddRequest(address=entry_pb2.EntryAddress(id="p", subarchitecture="vision"),
                                               value=value), metadata=metadata(handle, "a", "vision"), timeout=10)
        with pytest.raises(grpc.RpcError) as elsewhere:  # language is the other server's
            stub.Add(working_memory_pb2.AddRequest(
                address=entry_pb2.EntryAddress(id="q", subarchitecture="language"), value=value),
                metadata=metadata(handle, "b", "language", privileged=True), timeout=10)
        assert elsewhere.value.code() == grpc.StatusCode.NOT_FOUND
    finally:
        kill9(handle)
    again = serve(config, extra=("--server", "eyes"))
    try:
        stub = working_memory_pb2_grpc.WorkingMemoryStub(grpc.insecure_channel(again.endpoint))
        got = stub.Get(working_memory_pb2.GetRequest(address=entry_pb2.EntryAddress(id="p", subarchitecture="vision")),
                       metadata=metadata(again, "a", "vision"), timeout=10)
        assert got.entry.version == 0 and got.entry.revision == 1
    finally:
        again.stop()


def test_the_version_floor_survives_restarts_and_rises_after_a_crash_in_none(tmp_path: Path) -> None:
    # A new journal starts at 0, and a clean restart, or a crash in a mode that loses nothing a
    # reader saw, keeps the floor: versions stay a count of writes.
    for mode in ("always", "batch"):
        s = make(tmp_path / f"{mode}.db", mode)
        assert s.host.version_floor == 0
        s.host.add(A, "vision", "x", "t.T", b"")
        s.durable_sync()
        s2 = make(tmp_path / f"{mode}.db", mode)  # no close(): a crash, as above
        assert s2.host.version_floor == 0
        assert s2.host.overwrite(A, "vision", "x", "t.T", b"").version == 1
        s2.close()
    # In `none` a crash may have lost writes whose versions were seen: the next run starts above
    # every version stored and at least at its start time in µs, and keeps that floor.
    path = tmp_path / "none.db"
    s = make(path, "none")
    s.host.add(A, "vision", "x", "t.T", b"")
    for _ in range(5):
        s.host.overwrite(A, "vision", "x", "t.T", b"")
    s.close()
    s = make(path, "none")
    assert s.host.version_floor == 0  # clean shutdown: nothing lost
    s.durable_sync()
    before_us = time.time_ns() // 1000
    s2 = make(path, "none")  # no close(): a crash
    floor = s2.host.version_floor
    assert floor >= before_us
    assert s2.host.get(A, "vision", "x").version == 5  # the stored value keeps the version it had
    assert s2.host.overwrite(A, "vision", "x", "t.T", b"").version == floor
    s2.close()
    s3 = make(path, "none")
    assert s3.host.version_floor == floor
    s3.close()


def test_a_memory_only_system_starts_at_its_epoch_floor() -> None:
    before_us = time.time_ns() // 1000
    s = System("t", ["vision"])
    assert before_us <= s.host.version_floor <= time.time_ns() // 1000
    assert s.host.add(A, "vision", "x", "t.T", b"").version == s.host.version_floor


@pytest.mark.parametrize("mode", ["always", "batch", "none"])
def test_each_write_becomes_visible_exactly_once(tmp_path: Path, mode: str) -> None:
    s = make(tmp_path / "wm.db", mode)
    for i in range(10):
        s.host.add(A, "vision", f"e{i}", "t.T", b"")
    s.host.batch(A, [BatchOp(Operation.DELETE, "vision", f"e{i}") for i in range(5)])
    s.durable_sync()
    assert s.host.revision("vision") == 15
    assert [e.revision for e in s.host.events_since("vision", 1)] == list(range(1, 16))
    assert [r.id for r in s.host.all_entries("vision")] == [f"e{i}" for i in range(5, 10)]
    assert s.host.pending_writes() == 0
    s.close()


def test_closing_the_terminal_of_cast_serve_closes_its_journal_cleanly(tmp_path: Path) -> None:
    # SIGHUP (the window closed) stops the server as SIGTERM does: what is queued is written and the
    # journal marked clean, where the signal's default action ended the process in the middle.
    db = tmp_path / "wm.db"
    config = write_config(tmp_path / "system.yaml", {
        "system": "durable", "subarchitectures": {"vision": {}},
        "persistence": {"path": str(db), "durability": "batch"},
    })
    env = dict(os.environ, CAST_SECRET=SECRET, PYTHONPATH=PYTHONPATH)
    window = Terminal([str(VENV_BIN / "cast"), "serve", str(config), "--listen", "127.0.0.1:0"], env=env)
    try:
        window.wait_for("listening on ")
        window.close()
        assert window.proc.wait(timeout=60) == 0
    finally:
        window.end()
    journal = Journal(db, "batch")
    try:
        assert journal.was_clean
    finally:
        journal.close()
