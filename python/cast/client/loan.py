"""A large value written in place: :class:`Loan` (C++: ``cast::Loan``; Java: ``Loan``).

A camera driver that writes a frame the usual way makes the image's bytes,
then the message serialises them, then the library copies the result into
its staging area in shared memory. A loan skips both copies: the component
asks for the place of one top-level ``bytes`` field, fills it there, and
writes the loan instead of a message::

    frame = Frame(width=640, height=480, encoding="rgb8")
    with component.loan(frame, "pixels", 640 * 480 * 3) as loan:
        numpy.frombuffer(loan.buffer, dtype=numpy.uint8)[:] = camera.grab()
        component.overwrite("camera", loan)

On the server's host, with shared memory on, the buffer is in the session's
staging area and the write names it (nothing is copied on the client); else
(another host, shared memory off, a value under the threshold, a full staging
area) it is private memory and the write sends bytes as any other. Readers
get the same value either way (docs/client-protocol.md, "Writing a large
value in place").

The staged bytes are an ordinary serialised message: the value's other fields
first, then the loaned field, so the server needs nothing new.
"""

from __future__ import annotations

from types import TracebackType
from typing import Any

from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message

from cast.client.shm_session import ClientSession, Staged
from cast.errors import InvalidArgumentError
from cast.wire.values import varint

__all__ = ["Loan", "loan_header"]

_WIRE_LENGTH_DELIMITED = 2


def loan_header(value: Message, field: str, size: int) -> bytes:
    """What precedes a loan's bytes: ``value`` serialised, then the key and length of ``field``.

    InvalidArgumentError, naming the field and what would do, when ``field`` is
    not a top-level singular ``bytes`` field of ``value``, already holds bytes,
    or ``size`` is negative.
    """
    desc = value.DESCRIPTOR
    loanable = [f.name for f in desc.fields if f.type == FieldDescriptor.TYPE_BYTES and not _repeated(f)]
    found = desc.fields_by_name.get(field)
    if found is None:
        raise InvalidArgumentError(
            f"{desc.name} has no field '{field}': a loan is taken of one of its top-level bytes fields "
            f"({', '.join(loanable) or 'it has none'})"
        )
    if found.type != FieldDescriptor.TYPE_BYTES or _repeated(found):
        kind = ("a repeated " if _repeated(found) else "a ") + _type_name(found)
        raise InvalidArgumentError(
            f"field '{field}' of {desc.full_name} is {kind}: a loan is taken of a top-level singular bytes field"
        )
    held = len(getattr(value, field))
    if held:
        raise InvalidArgumentError(
            f"field '{field}' of {desc.full_name} already holds {held} bytes: leave it empty, the loan's buffer is "
            "its bytes"
        )
    if size < 0:
        raise InvalidArgumentError(f"a loan's size is a number of bytes, 0 or more, not {size}")
    return value.SerializeToString() + varint(found.number << 3 | _WIRE_LENGTH_DELIMITED) + varint(size)


def _repeated(field: Any) -> bool:  # a FieldDescriptor of either protobuf runtime
    return bool(field.is_repeated)


def _type_name(field: Any) -> str:
    names = {v: k[len("TYPE_"):].lower() for k, v in vars(FieldDescriptor).items() if k.startswith("TYPE_")}
    return names.get(field.type, "field")


class Loan:
    """The place of one ``bytes`` field of a value, to fill before writing it (``Component.loan``)."""

    __slots__ = ("_buffer", "_session", "_spent", "_staged", "_whole", "size", "subarchitecture", "type_name")

    def __init__(self, subarchitecture: str, type_name: str, header: bytes, size: int,
                 place: tuple[ClientSession, Staged, memoryview] | None = None) -> None:
        self.subarchitecture = subarchitecture
        self.type_name = type_name
        self.size = size
        self._session: ClientSession | None = None
        self._staged: Staged | None = None
        if place is None:
            self._whole = memoryview(bytearray(len(header) + size))
            self._whole[:len(header)] = header
        else:
            self._session, self._staged, self._whole = place  # the region, its header written
        self._buffer = self._whole[len(header):]
        self._spent = False

    @property
    def buffer(self) -> memoryview:
        """The field's bytes, writable, in place (their first contents are unspecified); released by the write."""
        if self._spent:
            raise ValueError("this loan was written or closed: its buffer is gone; take a new loan")
        return self._buffer

    @property
    def shared(self) -> bool:
        """Whether the buffer is in shared memory with the server (the write copies nothing)."""
        return self._staged is not None

    def take(self, subarchitecture: str, session: ClientSession | None) -> Staged | bytes:
        """For the write of this loan to ``subarchitecture`` over ``session``: its staged region, or its bytes.

        The region when it is in ``session`` (the writer's live session):
        the write names it, and gives it back after its reply. Else the
        value's bytes (a session renewed since the loan was taken leaves the
        region in the old one, given back here). The loan is spent either
        way. InvalidArgumentError, the loan untouched, when it was already
        written or closed, or taken for another subarchitecture.
        """
        if self._spent:
            raise InvalidArgumentError("this loan was already written (or closed): take a new loan for each write")
        if subarchitecture != self.subarchitecture:
            raise InvalidArgumentError(
                f"the loan was taken for subarchitecture '{self.subarchitecture}' and is written to "
                f"'{subarchitecture}': take it with subarchitecture '{subarchitecture}'"
            )
        self._spent = True
        staged, own = self._staged, self._session
        if staged is not None and own is session and session is not None and not session.dead:
            self._release()
            return staged
        data = bytes(self._whole)
        self._release()
        if staged is not None and own is not None:
            own.unstage(staged, known=True)
        return data

    def close(self) -> None:
        """Give an unwritten loan's place back; nothing for a written or closed one."""
        if self._spent:
            return
        self._spent = True
        self._release()
        if self._session is not None and self._staged is not None:
            self._session.unstage(self._staged, known=True)

    def _release(self) -> None:
        # The views go now, so that the staging area is unmapped with its session; an array the caller made
        # of the buffer still holds it, and the mapping goes with that array.
        for view in (self._buffer, self._whole):
            try:
                view.release()
            except BufferError:
                pass

    def __enter__(self) -> Loan:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def __del__(self) -> None:
        if hasattr(self, "_spent"):  # not when its constructor failed
            self.close()
