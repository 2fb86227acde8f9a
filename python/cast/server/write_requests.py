"""Write requests to core operations: shared by the unary WorkingMemory calls and the Write stream."""

from __future__ import annotations

from cast.client.conversions import any_to_type_data
from cast.core.records import BatchOp, LockMode, Operation
from cast.errors import CastError, InvalidArgumentError
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["batch_ops", "lock_mode", "write_op"]


def lock_mode(value: int) -> LockMode:
    """The lock mode of a request; INVALID_ARGUMENT naming the accepted values otherwise."""
    try:
        return LockMode(value)
    except ValueError:
        raise InvalidArgumentError(f"lock mode must be O, OD or ODR (1, 2 or 3), got {value}") from None


def write_op(req: wm_pb2.AddRequest | wm_pb2.OverwriteRequest | wm_pb2.DeleteRequest) -> BatchOp:
    """The core operation of one add, overwrite or delete request."""
    addr = req.address
    if isinstance(req, wm_pb2.AddRequest):
        type_name, data = any_to_type_data(req.value)
        return BatchOp(Operation.ADD, addr.subarchitecture, addr.id, type_name, data)
    expected = req.expected_version if req.HasField("expected_version") else None
    if isinstance(req, wm_pb2.OverwriteRequest):
        type_name, data = any_to_type_data(req.value)
        return BatchOp(Operation.OVERWRITE, addr.subarchitecture, addr.id, type_name, data, expected)
    return BatchOp(Operation.DELETE, addr.subarchitecture, addr.id, expected_version=expected)


def batch_ops(request: wm_pb2.BatchRequest) -> list[BatchOp]:
    """The core operations of a batch; an error names the failing operation's index."""
    ops = []
    for index, item in enumerate(request.operations):
        kind = item.WhichOneof("operation")
        if kind is None:
            raise InvalidArgumentError(f"batch operation {index} is empty: set add, overwrite or delete")
        try:
            ops.append(write_op(getattr(item, kind)))
        except CastError as exc:
            raise type(exc)(f"batch operation {index}: {exc.message}") from None
    return ops
