"""Helpers of the recording tests: `cast record` and `cast replay` processes against real servers, files read back.

Every server is a real `cast serve` on port 0 (tests/conftest.py); the recorder is the `cast` command in its own
process, signalled as a person would (SIGINT, SIGTERM); files are read with the mcap package's own readers.
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from cast.v1.entry_pb2 import ChangeEvent
from tests.conftest import PYTHONPATH, SECRET, VENV_BIN, ServerHandle, run_to_end, stop_process, wait_for

CAST = str(VENV_BIN / "cast")
COMPONENTS = Path(__file__).resolve().parent / "components"


def cli_env(**extra: str) -> dict[str, str]:
    """The environment of a `cast` command aimed at a test server: its secret, nothing of a `cast run`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    env.update(CAST_SECRET=SECRET, PYTHONPATH=PYTHONPATH, CAST_RUNTIME_DIR="/nonexistent-cast-runtime", **extra)
    return env


def cast(*args: str, timeout: float = 120, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """Run a `cast` command to its end; one still running after ``timeout`` fails with its threads' stacks."""
    return run_to_end([CAST, *args], f"cast {' '.join(args)}", timeout, env=env or cli_env())


@dataclass
class RecordProcess:
    """A running `cast record`, its stderr collected line by line."""

    process: subprocess.Popen[str]
    path: Path
    lines: list[str] = field(default_factory=list)

    def stderr(self) -> str:
        return "".join(self.lines)

    def stop(self, sig: int = signal.SIGINT) -> int:
        """Signal it as a person would and wait for its end; its exit status."""
        if self.process.poll() is None:
            self.process.send_signal(sig)
        try:
            return self.process.wait(60)
        finally:
            stop_process(self.process, 5)


def record(endpoint: str, path: Path, *args: str, env: dict[str, str] | None = None) -> RecordProcess:
    """Start `cast record --endpoint ENDPOINT -o PATH ARGS...` and wait until its watches are created.

    ``env``: its environment (:func:`cli_env` when None).
    """
    proc = subprocess.Popen([CAST, "record", "--endpoint", endpoint, "-o", str(path), *args], env=env or cli_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    handle = RecordProcess(proc, path)

    def drain() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            handle.lines.append(line)

    threading.Thread(target=drain, daemon=True).start()
    wait_for(lambda: "cast record: recording" in handle.stderr() or proc.poll() is not None, what="the recorder")
    assert proc.poll() is None, handle.stderr()
    return handle


@pytest.fixture
def recorders() -> Iterator[list[RecordProcess]]:
    """Recorders a test starts (append them); any still running at the end is stopped."""
    started: list[RecordProcess] = []
    yield started
    for r in started:
        stop_process(r.process, 5)


@dataclass
class Read:
    """A recording read back: every message with its channel and schema, and the file's metadata."""

    messages: list[tuple[Schema | None, Channel, Message]]
    metadata: dict[str, dict[str, str]]
    summary: Any

    def on(self, topic: str) -> list[Message]:
        return [m for _, c, m in self.messages if c.topic == topic]

    def topics(self) -> set[str]:
        return {c.topic for _, c, _ in self.messages}

    def channel(self, topic: str) -> Channel:
        (found,) = {c.id: c for _, c, _ in self.messages if c.topic == topic}.values()
        return found


def read_indexed(path: Path) -> Read:
    """Through the summary and chunk indexes, with CRC validation on; the file must be finished."""
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes, "no summary or no chunk index: the file is not finished"
        messages = list(reader.iter_messages(log_time_order=False))
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return Read(messages, metadata, summary)


def read_stream(path: Path) -> list[tuple[Channel, Message]]:
    """Front to back with the stream reader, CRCs validated (also the data section's)."""
    channels: dict[int, Channel] = {}
    out: list[tuple[Channel, Message]] = []
    with path.open("rb") as f:
        for record in StreamReader(f, validate_crcs=True).records:
            if isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                out.append((channels[record.channel_id], record))
    return out


def component_env(server: ServerHandle, component_id: str, sa: str) -> dict[str, str]:
    """The launch environment of a test component process, with this suite's components importable."""
    env = server.env(component_id, sa)
    env["PYTHONPATH"] = os.pathsep.join([str(COMPONENTS), env["PYTHONPATH"]])
    return env


def recorded_so_far(path: Path) -> list[ChangeEvent]:
    """The change records in the complete chunks of a file still being written (flushed at least every second)."""
    if not path.exists():
        return []
    channels: dict[int, Channel] = {}
    out: list[ChangeEvent] = []
    try:
        with path.open("rb") as f:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message) and channels[rec.channel_id].topic == "/cast/changes":
                    out.append(ChangeEvent.FromString(rec.data))
    except Exception:
        pass  # the chunk in progress, or the end of a file not finished yet
    return out


def wait_recorded(path: Path, count: int, what: str = "") -> list[ChangeEvent]:
    """Wait until the file holds at least ``count`` change records; those records."""
    return list(wait_for(lambda: (found := recorded_so_far(path)) and len(found) >= count and found,
                         what=what or f"{count} changes in {path.name}"))


@dataclass
class Scenario:
    """A recording of a small system in three phases a second apart, and what its WMs held at the end.

    Phase A (0 s): vision adds p1 and p2, motor's task manager decides a task; phase B (~1 s): vision overwrites
    p1, adds c1, deletes p2; phase C (~2 s): a privileged writer adds q1 to language.
    """

    path: Path
    final: dict[str, dict[str, tuple[str, str]]]  # SA -> id -> (type, value as text)


def entries(server: ServerHandle, sa: str) -> dict[str, tuple[str, str]]:
    """The Pose and Counter entries of an SA: id -> (type, value as text)."""
    from cast_testing_pb2 import Counter, Pose

    reader = server.connect("reader", sa)
    try:
        found = {}
        for cls in (Pose, Counter):
            for entry in reader.get_all(cls, subarchitecture=sa):
                found[entry.id] = (entry.type, text(entry.value))
        return found
    finally:
        reader._cast_close()


def text(value: Any) -> str:
    """A message as one line of text."""
    return " ".join(str(value).split())


@pytest.fixture(scope="session")
def scenario(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Scenario]:
    """Record the scenario once for the session (a real server and `cast record`)."""
    import time

    from cast_testing_pb2 import Counter, Pose

    import cast
    from tests.conftest import DEFAULT_CONFIG, start_server

    tmp = tmp_path_factory.mktemp("scenario")
    server = start_server(tmp / "server", DEFAULT_CONFIG)
    path = tmp / "scenario.mcap"
    rec = record(server.endpoint, path)
    writer = server.connect("w", "vision", privileged=True)
    manager = server.connect("m", "motor", cls=cast.ManagedComponent)
    try:
        writer.add("p1", Pose(x=1, label="p1"))
        writer.add("p2", Pose(x=2, label="p2"))
        assert isinstance(manager, cast.ManagedComponent)
        manager.propose_task("drive")
        time.sleep(1.0)  # spacing between phases, so that --from/--to can pick one; nothing is timed
        writer.overwrite("p1", Pose(x=1.5, label="p1b"))
        writer.add("c1", Counter(writer="w", value=1))
        writer.delete_entry("p2")
        time.sleep(1.0)
        writer.add("q1", Pose(label="q"), subarchitecture="language")
        wait_for(lambda: any(e.address.id == "q1" for e in recorded_so_far(path)), what="the last change recorded")
        final = {sa: entries(server, sa) for sa in ("vision", "language")}
        assert rec.stop(signal.SIGINT) == 0, rec.stderr()
    finally:
        writer._cast_close()
        manager._cast_close()
        stop_process(rec.process, 5)
        server.stop()
    assert final == {
        "vision": {"p1": ("cast.testing.Pose", 'x: 1.5 label: "p1b"'), "c1": ("cast.testing.Counter",
                                                                          'writer: "w" value: 1')},
        "language": {"q1": ("cast.testing.Pose", 'label: "q"')},
    }
    yield Scenario(path, final)
