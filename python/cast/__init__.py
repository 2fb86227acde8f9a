"""CAST on gRPC: working memories shared by robot components in Python, C++ and Java.

The public API of the Python client library and component model. Everything
a component author needs is importable from ``cast``.
"""

from cast.client.component import Component, LockGuard, ManagedComponent, UnmanagedComponent, WatchHandle
from cast.client.delivery import Delivery, Priority
from cast.client.filters import (
    ChangeFilter,
    address_filter,
    global_type_filter,
    local_type_filter,
    operation_filter,
    source_filter,
)
from cast.client.loan import Loan
from cast.client.script import Connection, connect
from cast.client.types import Entry, Task, WorkingMemoryAddress, WorkingMemoryChange
from cast.client.views import ValueView
from cast.core.policies import Decision, TaskPolicy
from cast.core.records import LockMode, Operation, WriteResult
from cast.core.tasks import TaskOutcome, TaskState
from cast.errors import (
    AlreadyExistsError,
    CastError,
    ConsistencyError,
    DeadlineExceededError,
    HistoryExpiredError,
    InternalError,
    InvalidArgumentError,
    LockedError,
    NotFoundError,
    PermissionDeniedError,
    ResourceExhaustedError,
    UnauthenticatedError,
    UnavailableError,
)

__all__ = [
    "AlreadyExistsError",
    "CastError",
    "ChangeFilter",
    "Component",
    "Connection",
    "ConsistencyError",
    "DeadlineExceededError",
    "Decision",
    "Delivery",
    "Entry",
    "HistoryExpiredError",
    "InternalError",
    "InvalidArgumentError",
    "Loan",
    "LockGuard",
    "LockMode",
    "LockedError",
    "ManagedComponent",
    "NotFoundError",
    "Operation",
    "PermissionDeniedError",
    "Priority",
    "ResourceExhaustedError",
    "Task",
    "TaskOutcome",
    "TaskPolicy",
    "TaskState",
    "UnauthenticatedError",
    "UnavailableError",
    "UnmanagedComponent",
    "ValueView",
    "WatchHandle",
    "WorkingMemoryAddress",
    "WorkingMemoryChange",
    "WriteResult",
    "address_filter",
    "connect",
    "global_type_filter",
    "local_type_filter",
    "operation_filter",
    "source_filter",
]
