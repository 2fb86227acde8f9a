"""What the wire adds to a :class:`System`: its own .proto files and the bytes of a task entry.

The core knows nothing of the wire (``cast.v1``); a server's System gets the
system's .proto files preloaded as the server's own (a client's copy of one is
ignored, cast.core.schemas) and writes every task's state into its
``cast.v1.Task`` entry encoded as that message, so tools can watch decisions.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from cast.core.system import System
from cast.core.tasks import TaskRecord
from cast.server.conversions import task_to_pb
from cast.v1 import directory_pb2, entry_pb2, inspection_pb2, task_manager_pb2, working_memory_pb2

__all__ = ["WIRE_FILES", "encode_task", "wire_system"]

WIRE_FILES = tuple(m.DESCRIPTOR for m in (directory_pb2, entry_pb2, inspection_pb2, task_manager_pb2,
                                            working_memory_pb2))
"""The system's own .proto files (cast/v1/*.proto)."""


def encode_task(task: TaskRecord) -> bytes:
    """A task's state as the bytes of its ``cast.v1.Task`` entry."""
    return task_to_pb(task).SerializeToString()


def wire_system(name: str, subarchitectures: Sequence[str], **options: Any) -> System:
    """A :class:`System` as a server hosts it: the wire's files preloaded, task entries encoded."""
    return System(name, subarchitectures, own_files=WIRE_FILES, encode_task=encode_task, **options)



