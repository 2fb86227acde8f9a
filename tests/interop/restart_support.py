"""What the C++ and Java reliability and session tests share: the restartable system's configuration,
a writer that rides out a server restart, and the Python side of the SIGKILL tests."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter

import cast
from cast.testing import wait_for
from tests.reliability.conftest import write_config


def restart_config(tmp: Path, persistence: bool) -> Path:
    """A vision + language system, journaled (durability batch) when ``persistence``."""
    config: dict[str, Any] = {"system": "rc", "subarchitectures": {"vision": {}, "language": {}}}
    if persistence:
        config["persistence"] = {"path": str(tmp / "wm.db"), "durability": "batch"}
    return write_config(tmp / "system.yaml", config)


def write_until(c: Any, prefix: str, n: int) -> None:
    """Write n entries, retrying those refused while the server is away."""
    for i in range(n):
        while True:
            try:
                c.add(f"{prefix}-{i}", Counter(value=i))
                break
            except cast.UnavailableError:
                time.sleep(0.05)
            except cast.AlreadyExistsError:
                break  # applied before the connection broke, acknowledgement lost


def eventually(predicate: Callable[[], Any], timeout: float = 30.0) -> Any:
    """The first truthy value of ``predicate`` within ``timeout`` seconds (cast.testing.wait_for); None if it
    never was one (the caller asserts, with the output that explains the failure)."""
    try:
        return wait_for(predicate, timeout)
    except AssertionError:
        return None


def readable(component: Any, entry_id: str) -> bool:
    """Whether ``entry_id`` can be read (no other component holds an ODR lock on it); takes no lock."""
    try:
        component.get(entry_id, Counter)
    except cast.LockedError:
        return False
    return True


class PyWorker(cast.ManagedComponent):
    """A Python component that records the tasks it adopts, to see when a killed component's slot frees."""

    def __init__(self) -> None:
        super().__init__()
        self.adopted: list[cast.Task] = []
        self.adopted_event = threading.Event()

    def task_adopted(self, task: cast.Task) -> None:
        self.adopted.append(task)
        self.adopted_event.set()


def holder_config(tmp: Path, holder: dict[str, Any]) -> Path:
    """A system whose one managed component "holder" (``holder`` says language and what to run) is
    restarted on failure, with one task slot in vision, so that a killed holder's task blocks others."""
    return write_config(tmp / "system.yaml", {
        "system": "restart",
        "subarchitectures": {"vision": {
            "task_manager": {"policy": "fifo", "max_concurrent": 1},
            "components": {"holder": {
                **holder, "kind": "managed", "restart": {"policy": "on-failure", "backoff": 0.2},
            }},
        }},
    })
