"""What a recorder costs: on the server's host its watch's events on a shared-memory session's socket and large
values lent; changes taken from its streams in batches.

A recorder takes every change of the system, so on the server's host its watch is served as a component's is
there (docs/client-protocol.md, "A watch's events on the session's socket"): the events come as EVENTS frames
read by the recorder's own dispatcher thread, and values above the session's threshold are lent by shared memory
and copied into the file. With ``CAST_SHARED_MEMORY=off`` the same changes come on the gRPC call. Either way the
file holds the same bytes. The recording loop takes what its streams delivered together rather than waking for
each change (cast.recording.recorder.BATCH_S).
"""

from __future__ import annotations

import queue
import threading
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.wrappers_pb2 import BytesValue

from cast.client import shm_session
from cast.client.credentials import TokenSource
from cast.recording.mcap_file import RecordingWriter
from cast.recording.recorder import RECORD_ID, Recorder, RecordOptions
from cast.wire import shared_memory as wire
from tests.conftest import ServerHandle, wait_for
from tests.recording.conftest import read_indexed

BIG = 1 << 20  # above every session's threshold (shared_memory.threshold_bytes, 64 KiB by default)


class _CountedQueue(queue.SimpleQueue):  # type: ignore[type-arg]
    """The recorder's queue, counting the takes that may wait (``get_nowait`` takes what is there)."""

    def __init__(self) -> None:
        self.waits = 0

    def get(self, block: bool = True, timeout: float | None = None) -> Any:
        self.waits += 1
        return super().get(block, timeout)


def _record(server: ServerHandle, path: Path, values: list[bytes],
            counted: _CountedQueue | None = None) -> list[tuple[int, str]]:
    """Record ``values`` written to "img" (added, then overwritten); the EVENTS frames read meanwhile, by thread.

    With ``counted`` the recorder queues its changes there.
    """
    frames: list[tuple[int, str]] = []
    original = shm_session.ClientSession._handle

    def spy(self: shm_session.ClientSession, frame: wire.Frame) -> None:
        if frame.kind == wire.EVENTS:
            frames.append((len(frame.body), threading.current_thread().name))
        original(self, frame)

    mp = pytest.MonkeyPatch()
    mp.setattr(shm_session.ClientSession, "_handle", spy)
    recorder = Recorder(server.endpoint, TokenSource(server.token(RECORD_ID, "")), RecordOptions(("vision",)))
    if counted is not None:
        recorder._queue = counted
    writer = server.connect("camera", "vision")
    stop = threading.Event()
    try:
        recorder.start()
        out = RecordingWriter(path, recorder.header())
        thread = threading.Thread(target=recorder.run, args=(out, stop, None, lambda gap: None), daemon=True)
        thread.start()
        if counted is not None:  # every change in one write: they reach the recorder together
            writer.batch([("add", f"v{i}", BytesValue(value=v)) for i, v in enumerate(values)])
        else:
            writer.add("img", BytesValue(value=values[0]))
            for value in values[1:]:
                writer.overwrite("img", BytesValue(value=value))
        wait_for(lambda: recorder.stats.changes >= len(values), what="every change recorded")
        stop.set()
        thread.join(30)
        assert not thread.is_alive(), "the recorder did not stop"
        out.finish(recorder.trailer())
    finally:
        stop.set()
        writer._cast_close()
        recorder.close()
        mp.undo()
    return frames


def _values(path: Path) -> list[bytes]:
    """The value messages of the file, in order (the change records left out)."""
    read = read_indexed(path)
    return [m.data for _, channel, m in read.messages if channel.topic.startswith("/vision/")]


def _images() -> list[bytes]:
    return [bytes([seed]) * BIG for seed in range(1, 4)] + [b"small"]


def test_on_the_servers_host_the_recorders_events_come_on_the_session_socket_and_large_values_are_lent(
    server: ServerHandle, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("CAST_SHARED_MEMORY", raising=False)
    path = tmp_path / "shared.mcap"
    images = _images()
    frames = _record(server, path, images)
    assert frames, "no EVENTS frame reached the recorder: its events came on the gRPC call"
    assert {name for _, name in frames} == {f"cast-dispatch-{RECORD_ID}"}, frames
    # A lent value's frame carries its reference, not its megabyte.
    assert max(size for size, _ in frames) < 64 << 10, frames
    assert [BytesValue.FromString(v).value for v in _values(path)] == images


def test_with_shared_memory_off_the_recorder_gets_the_same_changes_on_its_grpc_call(
    server: ServerHandle, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CAST_SHARED_MEMORY", "off")
    path = tmp_path / "bytes.mcap"
    images = _images()
    assert _record(server, path, images) == []
    assert [BytesValue.FromString(v).value for v in _values(path)] == images


def test_the_recording_loop_takes_what_its_streams_delivered_together_not_a_wake_up_per_change(
    server: ServerHandle, tmp_path: Path
) -> None:
    path = tmp_path / "batch.mcap"
    values = [f"value {i}".encode() for i in range(300)]
    counted = _CountedQueue()
    _record(server, path, values, counted)
    assert [BytesValue.FromString(v).value for v in _values(path)] == values
    # Taken one by one, each change is a take that may wait: 300 or more. Together, a handful.
    assert counted.waits < 30, counted.waits
