"""Across a SIGKILL of `cast serve`: nobody saw what the crash undid, and no version is given twice.

The journal's fault-injection file (`CAST_FAILPOINT_JOURNAL_HOLD`) keeps the
server's committer from writing while it exists, so a write is committed in
memory and not durable for as long as the test wants. Every version any caller
is told, before and after the kill, is recorded with the value it named: a
version that names two values is the lost update that versions exist to
prevent.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Counter
from google.protobuf import any_pb2

from cast.v1 import entry_pb2, inspection_pb2, inspection_pb2_grpc, working_memory_pb2, working_memory_pb2_grpc
from tests.conftest import ServerHandle
from tests.reliability.conftest import kill9, metadata, serve, wait_for, write_config

SA = "vision"


class Client:
    """Raw stubs of one component, remembering every (version, value) it was told."""

    def __init__(self, handle: ServerHandle, name: str, seen: dict[int, set[int]]) -> None:
        self.channel = grpc.insecure_channel(handle.endpoint)
        self.stub = working_memory_pb2_grpc.WorkingMemoryStub(self.channel)
        self.inspect = inspection_pb2_grpc.InspectionStub(self.channel)
        self.md = metadata(handle, name, SA)
        self.seen = seen

    def _address(self) -> entry_pb2.EntryAddress:
        return entry_pb2.EntryAddress(subarchitecture=SA, id="x")

    def _told(self, version: int, value: int) -> None:
        self.seen.setdefault(version, set()).add(value)

    def add(self, value: int) -> int:
        reply = self.stub.Add(working_memory_pb2.AddRequest(address=self._address(), value=_any(value)),
                              metadata=self.md, timeout=10)
        self._told(reply.version, value)
        return int(reply.version)

    def overwrite_future(self, value: int, expected: int | None = None) -> Any:
        request = working_memory_pb2.OverwriteRequest(address=self._address(), value=_any(value))
        if expected is not None:
            request.expected_version = expected
        return self.stub.Overwrite.future(request, metadata=self.md, timeout=30)

    def overwrite(self, value: int, expected: int | None = None) -> int:
        reply = self.overwrite_future(value, expected).result()
        self._told(reply.version, value)
        return int(reply.version)

    def get(self) -> tuple[int, int] | None:
        try:
            entry = self.stub.Get(working_memory_pb2.GetRequest(address=self._address()), metadata=self.md,
                                  timeout=10).entry
        except grpc.RpcError as exc:
            if exc.code() == grpc.StatusCode.NOT_FOUND:
                return None
            raise
        counter = Counter()
        entry.value.Unpack(counter)
        self._told(entry.version, counter.value)
        return counter.value, int(entry.version)

    def pending(self) -> int:
        reply = self.inspect.ListEntries(inspection_pb2.ListEntriesRequest(subarchitecture=SA), metadata=self.md,
                                         timeout=10)
        return int(reply.pending_writes)

    def close(self) -> None:
        self.channel.close()


def _any(value: int) -> any_pb2.Any:
    packed = any_pb2.Any()
    packed.Pack(Counter(value=value))
    return packed


def _config(tmp_path: Path, mode: str) -> Path:
    config: dict[str, Any] = {"system": "crash", "subarchitectures": {SA: {}}}
    if mode != "memory":
        config["persistence"] = {"path": "wm.db", "durability": mode}
    return write_config(tmp_path / "system.yaml", config)


def _start(tmp_path: Path, mode: str) -> tuple[Path, Path, dict[int, set[int]], ServerHandle]:
    """The hold file, the configuration, the versions seen so far, and `cast serve` with the failpoint."""
    hold = tmp_path / "hold"
    config = _config(tmp_path, mode)
    return hold, config, {}, serve(config, env={"CAST_FAILPOINT_JOURNAL_HOLD": str(hold)})


@contextmanager
def _clients(handle: ServerHandle, seen: dict[int, set[int]]) -> Iterator[tuple[Client, Client]]:
    """A writer and a reader on ``handle``, closed on the way out."""
    writer, reader = Client(handle, "writer", seen), Client(handle, "reader", seen)
    try:
        yield writer, reader
    finally:
        writer.close()
        reader.close()


@contextmanager
def _served_again(hold: Path, config: Path, seen: dict[int, set[int]]) -> Iterator[tuple[Client, Client]]:
    """Serve ``config`` again with the journal writing (``hold`` gone), and a writer and a reader on it."""
    hold.unlink()
    handle = serve(config)
    try:
        with _clients(handle, seen) as clients:
            yield clients
    finally:
        handle.stop()


def _one_value_per_version(seen: dict[int, set[int]]) -> None:
    reused = {version: values for version, values in seen.items() if len(values) > 1}
    assert not reused, f"versions given to more than one value: {reused}"


@pytest.mark.parametrize("mode", ["always", "batch"])
def test_a_write_the_journal_holds_is_seen_by_nobody_and_a_kill_then_reuses_no_version(
    tmp_path: Path, mode: str
) -> None:
    hold, config, seen, handle = _start(tmp_path, mode)
    try:
        with _clients(handle, seen) as (writer, reader):
            assert writer.add(1) == 0
            hold.touch()
            held = writer.overwrite_future(2)
            wait_for(lambda: reader.pending() == 1, what="the held overwrite to be committed in memory")
            # Committed, not durable: the reader sees the durable value, and a compare-and-set that the
            # held write would refuse gets no answer at all until the write is durable.
            assert reader.get() == (1, 0)
            cas = reader.overwrite_future(3, expected=0)
            with pytest.raises(grpc.FutureTimeoutError):
                cas.result(timeout=0.5)
            assert not held.done()
            kill9(handle)
            for future in (held, cas):
                with pytest.raises(grpc.RpcError) as err:
                    future.result()
                assert err.value.code() == grpc.StatusCode.UNAVAILABLE
    finally:
        kill9(handle)
    with _served_again(hold, config, seen) as (writer, reader):
        assert reader.get() == (1, 0)  # the held write is gone, and nobody had seen it
        assert writer.overwrite(4) == 1  # so version 1 is given now, for the first time
        assert reader.overwrite(5, expected=1) == 2
        _one_value_per_version(seen)


@pytest.mark.parametrize("mode", ["none", "memory"])
def test_a_restart_that_loses_acknowledged_writes_never_gives_their_versions_again(
    tmp_path: Path, mode: str
) -> None:
    hold, config, seen, handle = _start(tmp_path, mode)
    writer = Client(handle, "writer", seen)
    try:
        first = writer.add(1)
        for value in (2, 3):
            writer.overwrite(value)
    finally:
        writer.close()
        handle.stop()  # a clean stop: in `none` these three are on disk
    handle = serve(config, env={"CAST_FAILPOINT_JOURNAL_HOLD": str(hold)})
    hold.touch()  # from now on the journal writes nothing: acknowledged writes will be lost
    try:
        with _clients(handle, seen) as (writer, reader):
            if mode == "memory":
                assert reader.get() is None
                first = writer.add(11)
            else:
                assert reader.get() == (3, first + 2)
            for value in (12, 13, 14):
                writer.overwrite(value)
            last = reader.get()
            assert last is not None and last[0] == 14
    finally:
        kill9(handle)
    with _served_again(hold, config, seen) as (writer, reader):
        survived = reader.get()
        assert survived is None if mode == "memory" else survived == (3, 2)
        # The reader's compare-and-set on the version it last saw names a value that is gone:
        # it must fail, never apply to whatever holds that version number now.
        cas = reader.overwrite_future(20, expected=last[1])
        with pytest.raises(grpc.RpcError) as err:
            cas.result()
        assert err.value.code() in (grpc.StatusCode.ABORTED, grpc.StatusCode.NOT_FOUND)
        told_before = max(seen)
        new = writer.add(21) if survived is None else writer.overwrite(21)
        assert new > told_before, f"version {new} after the restart, but {told_before} was given before it"
        for value in (22, 23):
            writer.overwrite(value)
        reader.get()
        _one_value_per_version(seen)
