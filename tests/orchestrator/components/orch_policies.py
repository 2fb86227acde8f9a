"""A user task manager policy named in a test configuration (``policy: orch_policies:PrefixPolicy``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from cast import Decision, TaskPolicy


class PrefixPolicy(TaskPolicy):
    """Adopts tasks whose name starts with ``prefix``; rejects the rest."""

    name = "prefix"

    def __init__(self, prefix: str = "ok") -> None:
        self.prefix = prefix

    def decide(self, waiting: Sequence[Any], adopted: Sequence[Any], wm: Any) -> Decision:
        decision = Decision()
        for task in waiting:
            if task.name.startswith(self.prefix):
                decision.adopt.append(task)
            else:
                decision.reject.append((task, f"name does not start with '{self.prefix}'"))
        return decision

    def describe(self) -> str:
        return f"prefix({self.prefix})"
