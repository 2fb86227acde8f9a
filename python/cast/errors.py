"""The named errors of CAST, shared by the WM core, the server and the client library.

Every error corresponds to one gRPC status code (by name, so this module needs
no gRPC import). The server turns a raised error into that status; the client
library turns the status back into the same class, so a component sees the
same exception whether its WM is in-process or remote.
"""

from __future__ import annotations

__all__ = [
    "ERROR_TRAILER",
    "AlreadyExistsError",
    "CastError",
    "ConsistencyError",
    "DeadlineExceededError",
    "HistoryExpiredError",
    "InternalError",
    "InvalidArgumentError",
    "LockedError",
    "NoSessionError",
    "NotFoundError",
    "PermissionDeniedError",
    "ResourceExhaustedError",
    "SchemaConflictError",
    "TaskStateError",
    "UnauthenticatedError",
    "UnavailableError",
    "error_for_code",
]


class CastError(Exception):
    """Base class of every CAST error; ``code`` is the gRPC status code name."""

    code: str = "UNKNOWN"

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class AlreadyExistsError(CastError):
    """An entry with this id already exists (ALREADY_EXISTS)."""

    code = "ALREADY_EXISTS"


class NotFoundError(CastError):
    """The entry, subarchitecture or task does not exist (NOT_FOUND)."""

    code = "NOT_FOUND"


class ConsistencyError(CastError):
    """The entry's version is not the expected one (ABORTED)."""

    code = "ABORTED"


class PermissionDeniedError(CastError):
    """The component may not write where it tried to (PERMISSION_DENIED)."""

    code = "PERMISSION_DENIED"


class LockedError(CastError):
    """Another component holds a lock that forbids this (FAILED_PRECONDITION).

    Also raised for an unlock of an entry the caller does not hold.
    """

    code = "FAILED_PRECONDITION"


class SchemaConflictError(LockedError):
    """A schema file registered again with other types (FAILED_PRECONDITION).

    The class travels in the ``cast-error`` trailer, as for TaskStateError; a
    client that does not read it sees its FAILED_PRECONDITION error (LockedError).
    """


class TaskStateError(LockedError):
    """A task call its task's state does not allow, e.g. completing a task that is still waiting.

    FAILED_PRECONDITION on the wire, with the class named in the ``cast-error``
    trailer so that a client tells it from a lock refusal.
    """


class NoSessionError(LockedError):
    """A lock or a task asked for by a component with no live session (FAILED_PRECONDITION).

    Locks and tasks end with the session that took them; without one, nothing
    would ever release them.
    """


class InvalidArgumentError(CastError):
    """A bad id, type, value or request (INVALID_ARGUMENT)."""

    code = "INVALID_ARGUMENT"


class UnauthenticatedError(CastError):
    """The call had no valid token (UNAUTHENTICATED)."""

    code = "UNAUTHENTICATED"


class DeadlineExceededError(CastError):
    """The call's deadline passed before it could complete (DEADLINE_EXCEEDED)."""

    code = "DEADLINE_EXCEEDED"


class HistoryExpiredError(CastError):
    """A watch asked for (or fell behind to) revisions older than the kept history (OUT_OF_RANGE).

    The watcher must resynchronise: read the current state, then watch from the
    current revision.
    """

    code = "OUT_OF_RANGE"


class ResourceExhaustedError(CastError):
    """A configured limit was reached (RESOURCE_EXHAUSTED)."""

    code = "RESOURCE_EXHAUSTED"


class UnavailableError(CastError):
    """The server cannot be reached (UNAVAILABLE)."""

    code = "UNAVAILABLE"


class InternalError(CastError):
    """A bug: the server failed in a way it should not (INTERNAL)."""

    code = "INTERNAL"


_BY_CODE: dict[str, type[CastError]] = {
    cls.code: cls
    for cls in (
        AlreadyExistsError,
        NotFoundError,
        ConsistencyError,
        PermissionDeniedError,
        LockedError,
        InvalidArgumentError,
        UnauthenticatedError,
        DeadlineExceededError,
        HistoryExpiredError,
        ResourceExhaustedError,
        UnavailableError,
        InternalError,
    )
}


ERROR_TRAILER = "cast-error"
"""Trailing metadata key naming the error's class when a status code is shared by several."""


_BY_NAME: dict[str, type[CastError]] = {
    cls.__name__: cls for cls in (SchemaConflictError, TaskStateError, NoSessionError)
}


def error_for_code(code_name: str, message: str, name: str = "") -> CastError:
    """Return the named error for a gRPC status code name (``"NOT_FOUND"``, ...).

    ``name`` (the ``cast-error`` trailer) picks a more precise class of that
    code, such as TaskStateError for FAILED_PRECONDITION; an unknown one is ignored.
    """
    cls = _BY_CODE.get(code_name, CastError)
    precise = _BY_NAME.get(name)
    if precise is not None and precise.code == code_name:
        cls = precise
    err = cls(message)
    if cls is CastError:
        err.code = code_name
    return err
