"""Components the web view's tests run under `cast run`: a planner in `motor` that acts on goals posted in `vision`."""

from __future__ import annotations

from google.protobuf.wrappers_pb2 import StringValue

import cast


class Planner(cast.ManagedComponent):
    """Proposes a task ``plan-<id>`` for each goal (a StringValue) added to the `vision` WM; once adopted, reads the
    goal there and writes ``plan-<id>`` into its own SA's WM, then completes the task.

    So the motor SA watches and reads vision (cross-SA traffic), writes its own WM, and its task manager decides.
    """

    def start(self) -> None:
        self.on_change(cast.global_type_filter(StringValue, cast.Operation.ADD), self.goal)

    def goal(self, change: cast.WorkingMemoryChange) -> None:
        if change.subarchitecture == "vision":
            self.propose_task(f"plan-{change.id}")

    def task_adopted(self, task: cast.Task) -> None:
        goal_id = task.name.removeprefix("plan-")
        goal = self.get(goal_id, StringValue, subarchitecture="vision")
        self.add(task.name, StringValue(value=f"planned: {goal.value}"))
        self.task_complete(task, cast.TaskOutcome.SUCCEEDED, "planned")
