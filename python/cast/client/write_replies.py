"""A write request's reply: settled on its future, turned into its result or error, named in errors.

Shared by the two ways a component's Write-stream requests travel: the gRPC
``Write`` stream (:mod:`cast.client.write_stream`) and the shared-memory
session's socket (:mod:`cast.client.socket_writes`).
"""

from __future__ import annotations

from concurrent.futures import Future, InvalidStateError

from cast.errors import CastError, error_for_code
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["reply_result", "settle", "what"]


def reply_result(reply: wm_pb2.WriteReply) -> wm_pb2.WriteReply:
    """The reply itself if it carries a result; the error the unary call would have raised otherwise."""
    if reply.WhichOneof("result") == "error":
        error = reply.error
        raise error_for_code(error.code, error.message or error.code, error.error_class)
    return reply


def settle(future: Future[wm_pb2.WriteReply], reply: wm_pb2.WriteReply | None, error: CastError | None) -> None:
    """Complete ``future`` with ``reply``, or fail it with ``error``; nothing if it is settled already."""
    try:
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(reply)  # type: ignore[arg-type]
    except InvalidStateError:
        pass  # settled already: its deadline passed


def what(request: wm_pb2.WriteRequest) -> str:
    """How an error names the request: "add of 'x'", "lock of 'x'", "batch of 3 writes"."""
    kind = request.WhichOneof("operation") or "request"
    if kind == "batch":
        return f"batch of {len(request.batch.operations)} writes"
    body = getattr(request, kind)
    return f"{kind} of '{body.address.id}'"
