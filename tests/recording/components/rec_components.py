"""Components the recording tests run as processes: a watcher that prints every change it is given."""

from __future__ import annotations

import json
from typing import Any

from cast_testing_pb2 import Counter, Pose

import cast

TYPES: dict[str, Any] = {"cast.testing.Pose": Pose, "cast.testing.Counter": Counter}


class Watcher(cast.UnmanagedComponent):
    """Prints one JSON line per change of its SA (value as text), as a component under development would see it."""

    def start(self) -> None:
        self.on_change(cast.ChangeFilter(subarchitecture=self.subarchitecture, include_entry=True), self.changed)

    def changed(self, change: cast.WorkingMemoryChange) -> None:
        line: dict[str, Any] = {"op": change.operation.name, "id": change.id, "type": change.type,
                                "by": change.source_component}
        cls = TYPES.get(change.type)
        if cls is not None and change.operation is not cast.Operation.DELETE:
            line["value"] = str(change.entry(cls).value).replace("\n", " ").strip()
        print(json.dumps(line), flush=True)

    def run(self) -> None:
        print("WATCHING", flush=True)
        self.wait_for_stop()
