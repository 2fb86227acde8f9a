"""Metrics of known traffic from Python components, over gRPC and in process: the same exact counts both ways.

Counting is in the core's rulebook (cast.core.access), which both transports go through; these tests
fail if one of them skipped it or counted differently.
"""

from __future__ import annotations

import threading
from typing import Any

import pytest
from cast_testing_pb2 import Pose

import cast
from cast.core.metrics_view import COUNTERS
from cast.core.policies import make_policy
from cast.core.records import Identity, Limits
from cast.core.system import System
from cast.server.wire import wire_system
from tests.client.conftest import ThreadServer
from tests.client.test_component_api import Manager
from tests.conftest import wait_for

N_ADDS, N_READS = 5, 4
VALUE = Pose(x=1, label="cup")
BIG = Pose(x=2, label="a bigger cup")
SIZE, BIG_SIZE = len(VALUE.SerializeToString()), len(BIG.SerializeToString())


def known_traffic(make: Any, system: System) -> None:
    """From a component of SA language into vision's WM: N adds, 2 overwrites, 1 delete and one refused add;
    M reads by a component of vision; a lock wait; a task proposed, adopted, completed; a watcher in language."""
    writer = make(cast.UnmanagedComponent, "writer", "language", True)
    reader = make(Manager, "reader", "vision")
    reader.start()
    watcher = make(cast.UnmanagedComponent, "watcher", "language")
    seen: list[cast.WorkingMemoryChange] = []
    watcher.on_change(cast.global_type_filter(Pose, include_entry=True), seen.append)
    for i in range(N_ADDS):
        writer.add(f"x{i}", VALUE, subarchitecture="vision")
    writer.overwrite("x0", BIG, subarchitecture="vision")
    writer.overwrite("x1", BIG, subarchitecture="vision")
    writer.delete_entry("x4", subarchitecture="vision")
    with pytest.raises(cast.AlreadyExistsError):
        writer.add("x0", VALUE, subarchitecture="vision")
    assert reader.get("x0", Pose) == BIG
    assert reader.get("x2", Pose) == VALUE
    assert len(reader.get_all(Pose)) == 4
    assert reader.exists("x3")
    # A lock wait: the reader waits for the writer's lock.
    writer.lock("x3", cast.LockMode.O, subarchitecture="vision")
    waited = threading.Thread(target=lambda: reader.lock("x3", cast.LockMode.O, timeout=20).unlock())
    waited.start()
    wait_for(lambda: system.host._waiter_count == 1, what="the reader to wait")  # no public count of lock waiters
    writer.unlock("x3", subarchitecture="vision")
    waited.join(20)
    task = reader.propose_task("look")
    wait_for(lambda: reader.decisions, what="the adoption")
    reader.task_complete(task, cast.TaskOutcome.SUCCEEDED, "seen")
    wait_for(lambda: len(seen) == N_ADDS + 3, what="every Pose event")


def expected() -> dict[str, Any]:
    """The counts of :func:`known_traffic`, times left out."""

    def counts(**given: int) -> dict[str, int]:
        return {name: given.get(name, 0) for name in COUNTERS if not name.endswith("_s")}

    written = N_ADDS * SIZE + 2 * BIG_SIZE
    read = BIG_SIZE + SIZE + (2 * BIG_SIZE + 2 * SIZE)  # get x0, get x2, get_all (x0, x1, x2, x3)
    sent = N_ADDS * SIZE + 2 * BIG_SIZE + SIZE  # every add and overwrite, and the deleted x4 with its value
    vision = counts(reads=N_READS, entries_read=6, writes=N_ADDS + 3, adds=N_ADDS, overwrites=2, deletes=1,
                    bytes_in=written, bytes_out=read + sent, events=N_ADDS + 3, event_bytes=sent, locks=2,
                    lock_waits=1, tasks_proposed=1, tasks_adopted=1, tasks_completed=1)
    del vision["writes_refused"]
    return {
        "components": {
            "reader": {"subarchitecture": "vision", **counts(reads=N_READS, entries_read=6, bytes_out=read, locks=1,
                                                             lock_waits=1, tasks_proposed=1, tasks_adopted=1,
                                                             tasks_completed=1)},
            "watcher": {"subarchitecture": "language", **counts(events=N_ADDS + 3, event_bytes=sent, bytes_out=sent)},
            "writer": {"subarchitecture": "language", **counts(writes=N_ADDS + 3, adds=N_ADDS, overwrites=2, deletes=1,
                                                               writes_refused=1, bytes_in=written, locks=1)},
        },
        "vision": vision,
        "traffic": [
            {"from_sa": "language", "to_sa": "vision", "reads": 0, "writes": N_ADDS + 3, "bytes_in": written,
             "bytes_out": sent, "events": N_ADDS + 3},
            {"from_sa": "vision", "to_sa": "vision", "reads": N_READS, "writes": 0, "bytes_in": 0, "bytes_out": read,
             "events": 0},
        ],
    }


def counted(snapshot: dict[str, Any]) -> dict[str, Any]:
    """The counts of a snapshot, without the times (which are measured, never asserted)."""
    def untimed(d: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in d.items() if not k.endswith("_s") and k != "task_wait"}

    return {
        "components": {cid: untimed(c) for cid, c in snapshot["components"].items()},
        "vision": untimed(snapshot["subarchitectures"]["vision"]),
        "traffic": snapshot["traffic"],
    }


def test_known_traffic_from_python_components_gives_exact_counts(make_component: Any) -> None:
    system = make_component.system
    known_traffic(make_component, system)
    snapshot = system.metrics.snapshot()
    assert counted(snapshot) == expected()
    assert snapshot["subarchitectures"]["language"]["writes"] == 0
    watchers = snapshot["delivery_latency"]["watchers"]
    assert list(watchers) == ["watcher"] and watchers["watcher"]["count"] == N_ADDS + 3
    assert snapshot["subarchitectures"]["vision"]["task_wait"]["count"] == 1
    assert snapshot["components"]["reader"]["lock_wait_s"] > 0


def _fresh(transport: str) -> tuple[Any, System, Any]:
    system = wire_system("t", ["vision", "language"], policies={"vision": make_policy("fifo", {"max_concurrent": 1})},
                         limits=Limits(history_events=64))
    server = ThreadServer(system) if transport == "grpc" else None
    made: list[Any] = []

    def make(cls: Any, component_id: str, sa: str = "vision", privileged: bool = False) -> Any:
        from cast.client.grpc_transport import GrpcTransport
        from cast.client.local_transport import LocalTransport

        identity = Identity(component_id, sa, privileged)
        if server is not None:
            assert server.running is not None
            bound: Any = GrpcTransport(server.running.endpoint, server.signer.issue(identity), identity)
        else:
            bound = LocalTransport(system, identity)
        component = cls()
        component._cast_bind(bound)
        made.append(component)
        return component

    def close() -> None:
        for component in made:
            component._cast_close()
        if server is not None:
            server.stop()

    return make, system, close


def test_in_process_components_count_exactly_as_grpc_ones() -> None:
    snapshots = {}
    for transport in ("grpc", "in-process"):
        make, system, close = _fresh(transport)
        try:
            known_traffic(make, system)
            snapshots[transport] = system.metrics.snapshot()
        finally:
            close()
    grpc_counts, local_counts = (counted(snapshots[t]) for t in ("grpc", "in-process"))
    assert grpc_counts == local_counts
    for snap in snapshots.values():
        assert {k: v["count"] for k, v in snap["delivery_latency"]["watchers"].items()} == {"watcher": N_ADDS + 3}
        assert sorted(snap["subarchitectures"]) == ["language", "vision"]
