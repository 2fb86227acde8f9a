"""Write requests to core operations: shared by the unary WorkingMemory calls and the Write stream."""

from __future__ import annotations

from cast.core.access import Access
from cast.core.arena import Placed
from cast.core.records import BatchOp, LockMode, Operation
from cast.errors import CastError, InvalidArgumentError
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire.values import any_to_type_data

__all__ = ["batch_ops", "lock_mode", "write_op"]


def lock_mode(value: int) -> LockMode:
    """The lock mode of a request; INVALID_ARGUMENT naming the accepted values otherwise."""
    try:
        return LockMode(value)
    except ValueError:
        raise InvalidArgumentError(f"lock mode must be O, OD or ODR (1, 2 or 3), got {value}") from None


def _value(
    req: wm_pb2.AddRequest | wm_pb2.OverwriteRequest, access: Access | None
) -> tuple[str, bytes | memoryview, Placed | None]:
    """(type, bytes, where they were placed) of a request's value: in ``value``, or staged in shared memory."""
    type_name, value = any_to_type_data(req.value)
    if not req.HasField("staged_value"):
        return type_name, value, None
    entry_id = req.address.id
    if value:
        raise InvalidArgumentError(
            f"the value of entry '{entry_id}' has both bytes (value.value) and a staged_value: send one of them"
        )
    if access is None:
        raise InvalidArgumentError(f"the value of entry '{entry_id}' is staged in shared memory, which this call "
                                   "does not take: send the value's bytes (value.value)")
    staged = req.staged_value
    data, placed = access.staged(staged.session, staged.offset, staged.size, entry_id)
    return type_name, data, placed


def write_op(
    req: wm_pb2.AddRequest | wm_pb2.OverwriteRequest | wm_pb2.DeleteRequest, access: Access | None = None
) -> BatchOp:
    """The core operation of one add, overwrite or delete request.

    ``access``: the caller's, to take a value staged in its shared-memory
    session (:meth:`cast.core.access.Access.staged`).
    """
    addr = req.address
    if isinstance(req, wm_pb2.AddRequest):
        type_name, data, placed = _value(req, access)
        return BatchOp(Operation.ADD, addr.subarchitecture, addr.id, type_name, data, placed=placed)
    expected = req.expected_version if req.HasField("expected_version") else None
    if isinstance(req, wm_pb2.OverwriteRequest):
        type_name, data, placed = _value(req, access)
        return BatchOp(Operation.OVERWRITE, addr.subarchitecture, addr.id, type_name, data, expected, placed)
    return BatchOp(Operation.DELETE, addr.subarchitecture, addr.id, expected_version=expected)


def batch_ops(request: wm_pb2.BatchRequest, access: Access | None = None) -> list[BatchOp]:
    """The core operations of a batch; an error names the failing operation's index."""
    ops = []
    for index, item in enumerate(request.operations):
        kind = item.WhichOneof("operation")
        if kind is None:
            raise InvalidArgumentError(f"batch operation {index} is empty: set add, overwrite or delete")
        try:
            ops.append(write_op(getattr(item, kind), access))
        except CastError as exc:
            raise type(exc)(f"batch operation {index}: {exc.message}") from None
    return ops
