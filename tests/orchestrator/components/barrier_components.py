"""Components of the start-barrier tests (tests/orchestrator/test_start_barrier.py).

The C++ (cpp_client/tests/components/cast_test_barrier.cc) and Java
(java_client/src/test/java/cast/itest/Barrier*.java) twins take the same args and
write the same entries, so one system mixes all three languages.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

from google.protobuf.wrappers_pb2 import Int64Value

import cast
from cast import Operation


class BarrierWriter(cast.UnmanagedComponent):
    """Privileged; first thing in run(): adds ``<id>-0`` .. ``<id>-<count-1>``, then ``<id>-end``, to SA ``sa``."""

    def configure(self, args: dict[str, Any]) -> None:
        self.sa = str(args["sa"])
        self.count = int(args["count"])

    def run(self) -> None:
        for i in range(self.count):
            self.add(f"{self.component_id}-{i}", Int64Value(value=i), subarchitecture=self.sa)
        self.add(f"{self.component_id}-end", Int64Value(value=self.count), subarchitecture=self.sa)
        self.wait_for_stop()


class BarrierWatcher(cast.UnmanagedComponent):
    """Watches ADDs to its own SA from start(); at a writer's ``-end`` adds ``seen-<id>-<writer>``: how many it saw."""

    def start(self) -> None:
        self._seen: dict[str, int] = {}
        self._mutex = threading.Lock()
        self.on_change([cast.operation_filter(Operation.ADD, local=True)], self._added)

    def _added(self, change: cast.WorkingMemoryChange) -> None:
        if change.id.startswith("seen-"):
            return  # another watcher's report
        writer, _, rest = change.id.rpartition("-")
        with self._mutex:
            if rest != "end":
                self._seen[writer] = self._seen.get(writer, 0) + 1
                return
            seen = self._seen.get(writer, 0)
        self.add(f"seen-{self.component_id}-{writer}", Int64Value(value=seen))


class BarrierGate(cast.UnmanagedComponent):
    """Its start() returns only once the file ``gate`` exists: it holds everyone's run() back till then."""

    def configure(self, args: dict[str, Any]) -> None:
        self.gate = Path(args["gate"])

    def start(self) -> None:
        while not self.gate.exists():
            time.sleep(0.02)
        self.add("gate-opened", Int64Value(value=1))

    def run(self) -> None:
        self.add("gate-ran", Int64Value(value=1))
        self.wait_for_stop()


class FirstWrite(cast.UnmanagedComponent):
    """Adds ``ran-<id>`` (``ran-<id>-<pid>`` once that exists: a restart) to its own SA first thing in run()."""

    def run(self) -> None:
        entry_id = f"ran-{self.component_id}"
        self.add(f"{entry_id}-{os.getpid()}" if self.exists(entry_id) else entry_id, Int64Value(value=1))
        self.wait_for_stop()
