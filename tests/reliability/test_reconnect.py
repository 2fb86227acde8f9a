"""Reconnection of the Python client: watches resume without gap or duplicate, sessions re-register.

The server is killed (SIGKILL) and restarted on the same port, or the network
between client and server is cut by a proxy; components in this process keep
their objects and must carry on by themselves.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from cast_testing_pb2 import Counter

import cast
from cast.client.filters import ChangeFilter
from cast.core.records import Identity, LockMode
from cast.errors import HistoryExpiredError, UnavailableError
from tests.conftest import ServerHandle
from tests.reliability.conftest import kill9, serve, wait_for, write_config
from tests.reliability.proxy import Proxy


class Collector(cast.UnmanagedComponent):
    """Records every change it is given, and every watch failure."""

    def __init__(self) -> None:
        self.changes: list[tuple[str, int, str]] = []
        self.failures: list[cast.CastError] = []
        self._mu = threading.Lock()

    def record(self, change: Any) -> None:
        with self._mu:
            self.changes.append((change.subarchitecture, change.revision, change.id))

    def watch_failed(self, error: cast.CastError) -> None:
        self.failures.append(error)

    def revisions(self, sa: str) -> list[int]:
        with self._mu:
            return [r for s, r, _ in self.changes if s == sa]


def _config(tmp: Path, persistence: bool) -> Path:
    config: dict[str, Any] = {"system": "rc", "subarchitectures": {"vision": {}, "language": {}}}
    if persistence:
        config["persistence"] = {"path": str(tmp / "wm.db"), "durability": "batch"}
    return write_config(tmp / "system.yaml", config)


class _Restartable:
    """A `cast serve` that can be killed and started again on the same port."""

    def __init__(self, config: Path) -> None:
        self.config = config
        self.server = serve(config)
        self.port = self.server.endpoint.rpartition(":")[2]

    def kill(self) -> None:
        """SIGKILL, no clean-up."""
        kill9(self.server)

    def restart(self) -> None:
        """Start it again where it was."""
        self.server = serve(self.config, listen=f"127.0.0.1:{self.port}")


@contextmanager
def _watched(tmp: Path, persistence: bool) -> Iterator[tuple[_Restartable, Collector, cast.UnmanagedComponent]]:
    """A restartable server, a watcher (a :class:`Collector`) and a writer in `vision`, closed on the way out."""
    served = _Restartable(_config(tmp, persistence))
    components: list[Any] = []
    try:
        watcher = served.server.connect("watcher", "vision", cls=Collector)
        components.append(watcher)
        writer = served.server.connect("writer", "vision")
        components.append(writer)
        assert isinstance(watcher, Collector) and isinstance(writer, cast.UnmanagedComponent)
        yield served, watcher, writer
    finally:
        for c in components:
            c._cast_close()
        served.server.stop()


def _write_until(c: Any, prefix: str, n: int) -> int:
    """Write n entries, retrying those refused while the server is away; return how many were retried."""
    retried = 0
    for i in range(n):
        while True:
            try:
                c.add(f"{prefix}-{i}", Counter(value=i))
                break
            except UnavailableError:
                retried += 1
                time.sleep(0.05)
            except cast.AlreadyExistsError:
                break  # applied before the connection broke, acknowledgement lost
    return retried


def test_watch_resumes_without_gap_or_duplicate_after_a_server_restart(tmp_path: Path) -> None:
    with _watched(tmp_path, persistence=True) as (served, watcher, writer):
        watcher.on_change(ChangeFilter(subarchitecture="vision"), watcher.record)
        watcher.on_change(ChangeFilter(subarchitecture="language"), watcher.record)
        _write_until(writer, "a", 50)
        wait_for(lambda: len(watcher.revisions("vision")) >= 50, what="first events")
        served.kill()
        # While the server is away a call fails promptly with a clear error; it does not hang.
        started = time.monotonic()
        with pytest.raises(UnavailableError, match="unavailable"):
            writer.get("a-0", Counter)
        assert time.monotonic() - started < 25
        served.restart()
        _write_until(writer, "b", 50)
        top = writer.get_entry("b-49", Counter).revision
        wait_for(lambda: watcher.revisions("vision")[-1:] == [top], what="events after the restart")
        revs = watcher.revisions("vision")
        assert revs == list(range(1, top + 1)), "gap or duplicate"
        assert not watcher.failures
        # The session was registered again.
        wait_for(lambda: watcher._transport.sessions >= 2, what="re-registration")


def test_a_server_restarted_without_its_history_gets_the_resync_signal(tmp_path: Path) -> None:
    with _watched(tmp_path, persistence=False) as (served, watcher, writer):
        watcher.on_change(ChangeFilter(subarchitecture="vision"), watcher.record)
        _write_until(writer, "a", 5)
        wait_for(lambda: len(watcher.revisions("vision")) == 5, what="events")
        served.kill()
        served.restart()
        # The new server starts at revision 0 again: resuming at 6 would silently mix two histories.
        _write_until(writer, "b", 10)
        wait_for(lambda: watcher.failures, what="the resynchronise signal")
        assert isinstance(watcher.failures[0], HistoryExpiredError)
        assert "resynchronise" in watcher.failures[0].message
        assert watcher.revisions("vision") == [1, 2, 3, 4, 5]  # nothing from the other history


def test_a_cut_connection_releases_the_sessions_locks_and_the_watch_catches_up(server: ServerHandle) -> None:
    proxy = Proxy(server.endpoint)
    holder_via_proxy = ServerHandle(server.process, proxy.endpoint, server.config_path)
    holder = holder_via_proxy.connect("holder", "vision", cls=Collector)
    other = server.connect("other", "vision")
    try:
        holder.add("doc", Counter(value=1))
        holder.on_change(ChangeFilter(subarchitecture="vision"), holder.record)
        holder.lock("doc", LockMode.OD)
        assert not other.try_lock("doc")
        proxy.cut()
        # The server notices the broken streams, ends the session and releases the lock.
        wait_for(lambda: other.try_lock("doc"), what="the lock to be released")
        other.unlock("doc")
        for i in range(20):
            other.add(f"while-cut-{i}", Counter(value=i))
        proxy.restore()
        top = other.get_entry("while-cut-19", Counter).revision
        wait_for(lambda: holder.revisions("vision")[-1:] == [top], what="the watcher to catch up")
        first = holder.revisions("vision")[0]
        assert holder.revisions("vision") == list(range(first, top + 1))
        wait_for(lambda: holder._transport.sessions >= 2, what="re-registration")
        # Locks do not survive a disconnect: the holder must take it again.
        holder.lock("doc", LockMode.OD)
        assert server.signer.verify(server.token("holder", "vision")) == Identity("holder", "vision")
    finally:
        holder._cast_close()
        other._cast_close()
        proxy.close()
