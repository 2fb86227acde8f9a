"""Components the live-view tests run under `cast run`: a managed component whose tasks the task manager decides."""

from __future__ import annotations

from google.protobuf.wrappers_pb2 import StringValue

import cast


class Proposer(cast.ManagedComponent):
    """Proposes a task ``answer-<id>`` for each StringValue added to its SA, and completes each task adopted."""

    def start(self) -> None:
        self.on_change(cast.local_type_filter(StringValue, cast.Operation.ADD), self.asked)

    def asked(self, change: cast.WorkingMemoryChange) -> None:
        self.propose_task(f"answer-{change.id}")

    def task_adopted(self, task: cast.Task) -> None:
        self.task_complete(task, cast.TaskOutcome.SUCCEEDED, "answered")
