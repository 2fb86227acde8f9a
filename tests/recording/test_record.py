"""`cast record`: every change in the file once, in order, with its schema, commit time and metadata; a finished,
indexed file after SIGINT, SIGTERM and --for; the choice of SAs, types and start revision; bad input refused."""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter, Pose
from google.protobuf import descriptor_pb2
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

import cast
from cast.client.filters import ChangeFilter
from cast.v1.entry_pb2 import ChangeEvent
from tests.conftest import ServerHandle, wait_for
from tests.recording.conftest import (
    CAST,
    RecordProcess,
    cli_env,
    read_indexed,
    read_stream,
    record,
    recorded_so_far,
    wait_recorded,
)
from tests.recording.conftest import cast as cast_cli
from tests.terminal import Terminal

OPS = {1: "ADD", 2: "OVERWRITE", 3: "DELETE"}


class Seen(cast.UnmanagedComponent):
    """The test's own watcher: every change of every SA, with its entry, as the server sent it."""

    def __init__(self) -> None:
        self.changes: list[Any] = []
        self._mu = threading.Lock()

    def seen(self, change: cast.WorkingMemoryChange) -> None:
        with self._mu:
            self.changes.append(change)

    def count(self, sa: str) -> int:
        with self._mu:
            return sum(1 for c in self.changes if c.subarchitecture == sa)


class Manager(cast.ManagedComponent):
    """Proposes tasks; the decisions arrive as cast.v1.Task changes."""


def test_a_recording_holds_every_change_once_with_its_schema_commit_time_and_metadata(
    server: ServerHandle, tmp_path: Path, recorders: list[RecordProcess]
) -> None:
    path = tmp_path / "all.mcap"
    rec = record(server.endpoint, path)
    recorders.append(rec)
    watcher = server.connect("watcher", "vision", cls=Seen)
    writer = server.connect("w", "vision")
    boss = server.connect("boss", "language", privileged=True)
    manager = server.connect("m", "motor", cls=Manager)
    assert isinstance(watcher, Seen) and isinstance(manager, Manager)
    try:
        for sa in ("vision", "language", "motor"):
            watcher.on_change(ChangeFilter(subarchitecture=sa, include_entry=True), watcher.seen)
        writer.add("p1", Pose(x=1, label="one"))
        writer.overwrite("p1", Pose(x=2, label="two", tags=["a", "b"]))
        writer.add("c1", Counter(writer="w", value=7))
        writer.delete_entry("p1")
        boss.add("g1", Pose(label="goal"), subarchitecture="motor")  # a privileged write into another SA
        task = manager.propose_task("drive", Pose(label="there"))
        wait_for(lambda: watcher.count("motor") >= 2, what="the task's change")
        manager.task_complete(task, cast.TaskOutcome.SUCCEEDED, "done")
        wait_for(lambda: watcher.count("motor") >= 3, what="the completion's change")
        total = len(watcher.changes)
        wait_recorded(path, total)
        assert rec.stop(signal.SIGINT) == 0, rec.stderr()
        seen = list(watcher.changes)
    finally:
        for c in (watcher, writer, boss, manager):
            c._cast_close()

    read = read_indexed(path)
    stream = read_stream(path)
    # The indexed reader (summary, chunk indexes) and the stream reader (front to back) agree, CRCs checked by both.
    assert [(c.topic, m.sequence, m.log_time, m.data) for _, c, m in read.messages] == [
        (c.topic, m.sequence, m.log_time, m.data) for c, m in stream]
    assert read.topics() == {"/vision/cast.testing.Pose", "/vision/cast.testing.Counter", "/motor/cast.testing.Pose",
                             "/motor/cast.v1.Task", "/cast/changes"}

    # Channels: protobuf, each with its type's registered FileDescriptorSet and metadata naming SA and type.
    for _, channel, _ in read.messages:
        assert channel.message_encoding == "protobuf"
    schemas = {c.topic: s for s, c, _ in read.messages}
    pose_channel = read.channel("/vision/cast.testing.Pose")
    assert pose_channel.metadata == {"cast.role": "value", "cast.subarchitecture": "vision",
                                     "cast.type": "cast.testing.Pose", "cast.schema": "registered"}
    pose_schema = schemas["/vision/cast.testing.Pose"]
    assert pose_schema is not None and pose_schema.encoding == "protobuf" and pose_schema.name == "cast.testing.Pose"
    files = descriptor_pb2.FileDescriptorSet.FromString(pose_schema.data).file
    assert [f.name for f in files] == ["cast_testing.proto"]
    task_schema = schemas["/motor/cast.v1.Task"]
    assert task_schema is not None and "cast/v1/task_manager.proto" in [
        f.name for f in descriptor_pb2.FileDescriptorSet.FromString(task_schema.data).file]
    assert read.channel("/cast/changes").metadata == {"cast.role": "changes"}

    # Every change the watcher saw is in the file once, in revision order per SA, at the server's commit time.
    changes = [(m, ChangeEvent.FromString(m.data)) for m in read.on("/cast/changes")]
    assert len(changes) == len(seen)
    for sa in ("vision", "language", "motor"):
        ours = [(c.revision, c.operation.name, c.id, c.type, c.version, c.source_component, c.source_subarchitecture,
                 c.time_ns) for c in seen if c.subarchitecture == sa]
        recorded = [(e.revision, OPS[e.operation], e.address.id, e.type, e.version, e.source_component,
                     e.source_subarchitecture, m.log_time) for m, e in changes if e.address.subarchitecture == sa]
        assert recorded == ours, sa
    vision = [e for _, e in changes if e.address.subarchitecture == "vision"]
    assert [(OPS[e.operation], e.address.id, e.revision) for e in vision] == [
        ("ADD", "p1", 1), ("OVERWRITE", "p1", 2), ("ADD", "c1", 3), ("DELETE", "p1", 4)]
    assert vision[1].entry.author == "w" and vision[1].entry.version == vision[1].version
    assert not vision[1].entry.HasField("value")  # the value travels on its own channel
    goal = next(e for _, e in changes if e.address.id == "g1")
    assert (goal.source_component, goal.source_subarchitecture) == ("boss", "language")

    # Values decode through the recorded schema to what was written; a delete has no value; change and value share
    # their sequence number.
    values = {m.sequence: (c.topic, m) for _, c, m in read.messages if c.topic != "/cast/changes"}
    delete = next(m for m, e in changes if OPS[e.operation] == "DELETE")
    assert delete.sequence not in values
    with path.open("rb") as f:
        decoded = {(c.topic, m.sequence): d for _, c, m, d in
                   make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()}
    overwrite = next(m for m, e in changes if OPS[e.operation] == "OVERWRITE" and e.address.id == "p1")
    pose = decoded[("/vision/cast.testing.Pose", overwrite.sequence)]
    assert (pose.x, pose.label, list(pose.tags)) == (2.0, "two", ["a", "b"])
    counter = decoded[("/vision/cast.testing.Counter", next(m.sequence for m, e in changes if e.address.id == "c1"))]
    assert (counter.writer, counter.value) == ("w", 7)
    assert all(values[m.sequence][1].log_time == m.log_time for m, e in changes if m.sequence in values)

    # Task decisions are ordinary cast.v1.Task changes.
    tasks = [d for (topic, _), d in decoded.items() if topic == "/motor/cast.v1.Task"]
    assert tasks and {t.name for t in tasks} == {"drive"} and {t.component for t in tasks} == {"m"}
    assert tasks[-1].outcome == 1  # TASK_OUTCOME_SUCCEEDED

    header = read.metadata["cast.recording"]
    assert header["system"] == "test" and header["subarchitectures"] == "vision,language,motor"
    assert header["endpoint"] == server.endpoint and header["format"] == "1"
    assert read.metadata["cast.recording.end"]["reason"] == "SIGINT"
    assert read.metadata["cast.recording.end"]["changes"] == str(len(seen))
    assert f"{len(seen)} changes" in rec.stderr()


def test_sigterm_while_writers_write_leaves_a_finished_file_with_every_revision_once(
    server: ServerHandle, tmp_path: Path, recorders: list[RecordProcess]
) -> None:
    path = tmp_path / "busy.mcap"
    rec = record(server.endpoint, path, "--sa", "vision")
    recorders.append(rec)
    writer = server.connect("w", "vision")
    stop = threading.Event()

    def write() -> None:
        i = 0
        while not stop.is_set():
            writer.add(f"n{i}", Counter(value=i))
            i += 1

    thread = threading.Thread(target=write, daemon=True)
    thread.start()
    try:
        wait_recorded(path, 50)
        assert rec.stop(signal.SIGTERM) == 0, rec.stderr()  # while the writer still writes
    finally:
        stop.set()
        thread.join(10)
        writer._cast_close()
    read = read_indexed(path)
    revisions = [ChangeEvent.FromString(m.data).revision for m in read.on("/cast/changes")]
    assert revisions == list(range(revisions[0], revisions[0] + len(revisions))) and len(revisions) >= 50
    assert len(read.on("/vision/cast.testing.Counter")) == len(revisions)
    assert read.summary.statistics.message_count == 2 * len(revisions)
    assert read.metadata["cast.recording.end"]["reason"] == "SIGTERM"


def test_sa_type_and_from_revision_choose_what_is_recorded_and_for_stops_by_itself(
    server: ServerHandle, tmp_path: Path
) -> None:
    writer = server.connect("w", "vision", privileged=True)
    try:
        writer.add("a", Pose(label="before"))  # vision revision 1, before the recorder started
        writer.add("b", Counter(value=1))  # 2
        writer.add("x", Pose(label="other SA"), subarchitecture="language")
        path = tmp_path / "chosen.mcap"
        rec = record(server.endpoint, path, "--sa", "vision", "--type", "cast.testing.Pose", "--from-revision", "1",
                     "--for", "3")
        writer.overwrite("b", Counter(value=2))  # 3: another type
        writer.add("c", Pose(label="after"))  # 4
        writer.add("y", Pose(label="other SA"), subarchitecture="language")
        assert rec.process.wait(60) == 0, rec.stderr()  # --for 3: it stopped by itself
    finally:
        writer._cast_close()
    read = read_indexed(path)
    changes = [ChangeEvent.FromString(m.data) for m in read.on("/cast/changes")]
    assert [(e.address.subarchitecture, e.address.id, e.revision) for e in changes] == [
        ("vision", "a", 1), ("vision", "c", 4)]
    assert read.topics() == {"/vision/cast.testing.Pose", "/cast/changes"}
    header = read.metadata["cast.recording"]
    assert (header["subarchitectures"], header["types"], header["from_revision"]) == ("vision", "cast.testing.Pose",
                                                                                       "1")
    assert read.metadata["cast.recording.end"]["reason"] == "time"


def test_a_recorder_killed_outright_leaves_its_flushed_chunks_and_the_tools_say_the_file_is_unfinished(
    server: ServerHandle, tmp_path: Path, recorders: list[RecordProcess]
) -> None:
    path = tmp_path / "killed.mcap"
    rec = record(server.endpoint, path)
    recorders.append(rec)
    writer = server.connect("w", "vision")
    try:
        for i in range(5):
            writer.add(f"k{i}", Counter(value=i))
        wait_recorded(path, 5)  # flushed within a second, without waiting for a chunk to fill
    finally:
        writer._cast_close()
    rec.stop(signal.SIGKILL)
    assert len(recorded_so_far(path)) == 5
    for command in ("info", "replay"):
        out = cast_cli(command, str(path), "--endpoint", server.endpoint) if command == "replay" else cast_cli(
            command, str(path))
        assert out.returncode == 2 and "is truncated" in out.stderr and "Ctrl-C and SIGTERM" in out.stderr, out.stderr


def test_bad_input_is_refused_naming_what_is_wrong_and_writes_no_file(server: ServerHandle, tmp_path: Path) -> None:
    existing = tmp_path / "existing.mcap"
    existing.write_bytes(b"keep me")
    out = cast_cli("record", "--endpoint", server.endpoint, "-o", str(existing), "--for", "1")
    assert out.returncode == 2 and f"{existing} exists" in out.stderr and "never overwritten" in out.stderr
    assert existing.read_bytes() == b"keep me"

    path = tmp_path / "never.mcap"
    out = cast_cli("record", "--endpoint", server.endpoint, "-o", str(path), "--sa", "visoin", "--for", "1")
    assert out.returncode == 2, out.stderr
    assert "no subarchitecture 'visoin' in system 'test' (known: vision, language, motor)" in out.stderr
    out = cast_cli("record", "--endpoint", server.endpoint, "-o", str(path), "--from-revision", "5", "--for", "1")
    assert out.returncode == 2 and "in the future" in out.stderr, out.stderr
    out = cast_cli("record", "--endpoint", server.endpoint, "-o", str(path), "--for", "0")
    assert out.returncode == 2 and "--for 0" in out.stderr
    out = cast_cli("record", "--endpoint", "127.0.0.1:1", "-o", str(path), "--for", "1")
    assert out.returncode == 2 and "no system answers at 127.0.0.1:1" in out.stderr, out.stderr
    empty = tmp_path / "empty.token"
    empty.write_text("\n")
    out = cast_cli("record", "--endpoint", server.endpoint, "-o", str(path), "--for", "1",
                   env=cli_env(CAST_TOKEN_FILE=str(empty)))
    assert out.returncode == 2 and f"CAST_TOKEN_FILE names {empty}, which is empty" in out.stderr, out.stderr
    assert not path.exists()


def test_a_start_older_than_the_history_is_refused_with_what_the_server_keeps(
    server_factory: Any, tmp_path: Path
) -> None:
    small = server_factory({"system": "small", "subarchitectures": {"vision": {}},
                            "limits": {"history_events": 5}})
    writer = small.connect("w", "vision")
    try:
        for i in range(12):
            writer.add(f"k{i}", Counter(value=i))
    finally:
        writer._cast_close()
    path = tmp_path / "old.mcap"
    out = cast_cli("record", "--endpoint", small.endpoint, "-o", str(path), "--from-revision", "1", "--for", "1")
    assert out.returncode == 2, out.stderr
    assert "revision 1 is no longer in the history (kept: 8..12)" in out.stderr
    assert not path.exists()


def test_on_a_terminal_a_live_line_shows_changes_bytes_and_rate(server: ServerHandle, tmp_path: Path) -> None:
    import os
    import pty
    import subprocess

    from tests.recording.conftest import CAST, cli_env

    primary, secondary = pty.openpty()
    path = tmp_path / "tty.mcap"
    proc = subprocess.Popen([CAST, "record", "--endpoint", server.endpoint, "-o", str(path), "--for", "4"],
                            env=cli_env(TERM="xterm"), stdout=subprocess.DEVNULL, stderr=secondary)
    os.close(secondary)
    seen = bytearray()

    def read() -> None:
        while True:
            try:
                chunk = os.read(primary, 4096)
            except OSError:
                return
            if not chunk:
                return
            seen.extend(chunk)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    writer = server.connect("w", "vision")
    try:
        wait_for(lambda: b"recording to" in seen, what="the live line")
        for i in range(3):
            writer.add(f"t{i}", Counter(value=i))
        wait_for(lambda: b"3 changes, " in seen, what="the live line to count the changes")
        assert proc.wait(60) == 0
    finally:
        writer._cast_close()
        if proc.poll() is None:
            proc.kill()
        reader.join(5)
        os.close(primary)
    text = seen.decode(errors="replace")
    assert "recording to tty.mcap: " in text and "KiB, " in text and "/s" in text


def test_a_cast_run_system_on_two_servers_is_found_through_its_runtime_directory(tmp_path: Path) -> None:
    import subprocess

    from tests.orchestrator.conftest import start_cast_run, write_config
    from tests.recording.conftest import CAST

    config = write_config(tmp_path / "two.yaml", {
        "system": "two",
        "subarchitectures": {
            "vision": {"task_manager": {"policy": "fifo", "max_concurrent": 1}, "components": {
                "worker": {"kind": "managed", "class": "orch_components:Worker", "args": {"source_sa": "motor"}}}},
            "motor": {"components": {"producer": {"class": "orch_components:Producer", "args": {"count": 2}}}},
        },
        "servers": {"main": {"subarchitectures": ["vision"]}, "motion": {"subarchitectures": ["motor"]}},
    })
    run = start_cast_run(tmp_path, config)
    try:
        wait_for(lambda: len(run.cli_json("ls", "vision")) >= 2, what="the worker's results")
        path = tmp_path / "two.mcap"
        out = subprocess.run([CAST, "record", "-o", str(path), "--from-revision", "1", "--for", "2"], cwd=tmp_path,
                             env=run.cli_environment(), capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
    finally:
        assert run.stop() == 0, run.output()
    read = read_indexed(path)
    changes = [ChangeEvent.FromString(m.data) for m in read.on("/cast/changes")]
    motor = [(e.address.id, e.revision) for e in changes if e.address.subarchitecture == "motor"]
    assert motor[:2] == [("item-0", 1), ("item-1", 2)]  # from the other server
    assert {e.address.subarchitecture for e in changes} == {"vision", "motor"}
    assert "/vision/cast.v1.Task" in read.topics() and "/motor/google.protobuf.StringValue" in read.topics()
    assert read.metadata["cast.recording"]["system"] == "two"


def test_closing_its_terminal_finishes_the_file(server: ServerHandle, tmp_path: Path) -> None:
    path = tmp_path / "window.mcap"
    window = Terminal([CAST, "record", "--endpoint", server.endpoint, "-o", str(path)], env=cli_env(TERM="xterm"))
    writer = server.connect("w", "vision")
    try:
        window.wait_for("recording to")  # the live line
        for i in range(3):
            writer.add(f"h{i}", Counter(value=i))
        wait_recorded(path, 3)
        window.close()
        assert window.proc.wait(timeout=60) == 0
    finally:
        writer._cast_close()
        window.end()
    read = read_indexed(path)
    assert len(read.on("/cast/changes")) == 3
    assert read.metadata["cast.recording.end"]["reason"] == "SIGHUP"
