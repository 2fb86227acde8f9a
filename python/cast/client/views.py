"""A value read without copying: :class:`ValueView` (C++: ``cast::ValueView``; Java: ``ValueView``).

``component.get_view(id)`` and ``change.view()`` give the serialised value as
a read-only ``memoryview``: on the server's host, of the shared memory the
server lent it in (nothing copied, however large); elsewhere, of the bytes
received. ``view.field(n)`` is the bytes of one top-level field (an image's
pixels in a ``bytes`` field), which numpy wraps without a copy::

    with component.get_view("camera") as view:
        pixels = numpy.frombuffer(view.field(1), dtype=numpy.uint8)

The bytes never change while the view is held; it is given back by
:meth:`ValueView.release` (the end of the ``with`` block) or when it is
garbage. Memoryviews and arrays made from it are valid while it is held.
"""

from __future__ import annotations

import builtins

from cast.client.shm_session import native_module
from cast.client.types import M, WorkingMemoryAddress, decode
from cast.core.records import EntryRecord
from cast.errors import InvalidArgumentError

__all__ = ["ValueView", "field_of"]

_native = native_module()  # field_of in C where the build has it (docs/decisions.md, "Claims, leases and fields in C")


def _varint(data: memoryview, at: int, what: str) -> tuple[int, int]:
    value = shift = 0
    while True:
        if at >= len(data) or shift > 63:
            raise InvalidArgumentError(f"{what}: the value ends inside a varint: it is not a serialised message")
        byte = data[at]
        at += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, at
        shift += 7


def field_of(data: memoryview, number: int, what: str = "the value") -> memoryview:
    """The bytes of top-level field ``number`` (bytes, string or message) of a serialised message, not copied.

    The last occurrence wins, as when protobuf parses it; an absent field is
    empty. A field of another kind (a number) is InvalidArgumentError.
    """
    found = data[0:0]
    at, size = 0, len(data)
    while at < size:
        key, at = _varint(data, at, what)
        tag, kind = key >> 3, key & 7
        if kind == 0:
            _, at = _varint(data, at, what)
        elif kind == 1:
            at += 8
        elif kind == 5:
            at += 4
        elif kind == 2:
            length, at = _varint(data, at, what)
            if tag == number:
                found = data[at: at + length]
            at += length
        else:
            raise InvalidArgumentError(f"{what}: field {tag} has wire type {kind}, which a view does not read")
        if tag == number and kind != 2:
            raise InvalidArgumentError(f"{what}: field {number} is a number, not bytes, a string or a message")
        if at > size:
            raise InvalidArgumentError(f"{what}: field {tag} runs past the end: it is not a serialised message")
    return found


class ValueView:
    """An entry's value, serialised, as a read-only view that is not a copy; metadata as :class:`cast.Entry`."""

    __slots__ = ("__weakref__", "_record", "_views")

    def __init__(self, record: EntryRecord) -> None:
        self._record: EntryRecord | None = record  # holds the value: shared memory stays lent while it is here
        self._views: list[memoryview] = []

    def _held(self) -> EntryRecord:
        if self._record is None:
            raise InvalidArgumentError("this view was released: read the entry again")
        return self._record

    @property
    def address(self) -> WorkingMemoryAddress:
        """Where the entry lives."""
        record = self._held()
        return WorkingMemoryAddress(record.id, record.subarchitecture)

    @property
    def id(self) -> str:
        """The entry's id."""
        return self._held().id

    @property
    def type(self) -> str:
        """The full message name of the value."""
        return self._held().type

    @property
    def version(self) -> int:
        """The entry's version this value is of."""
        return self._held().version

    @property
    def author(self) -> str:
        """The component that wrote it."""
        return self._held().author

    @property
    def revision(self) -> int:
        """The WM revision of the write."""
        return self._held().revision

    @property
    def modified_ns(self) -> int:
        """When it was written (server clock, ns since the epoch)."""
        return self._held().modified_ns

    @property
    def shared(self) -> bool:
        """Whether the bytes are in shared memory (lent by the server on this host), not a received copy."""
        record = self._record  # not through _held: an image callback reads this at every frame
        return (record if record is not None else self._held()).shared is not None

    @property
    def data(self) -> memoryview:
        """The serialised value, read-only."""
        view = memoryview(self._held().data).toreadonly()
        self._views.append(view)
        return view

    def field(self, number: int) -> memoryview:
        """The bytes of top-level field ``number`` (a ``bytes``, string or message field), read-only, not copied."""
        record = self._record  # as data does, not through it: an image callback reads this at every frame
        if record is None:
            record = self._held()
        data = memoryview(record.data).toreadonly()
        self._views.append(data)
        found = _native.field_of(data, number) if _native is not None else None
        if found is not None:
            return found  # type: ignore[no-any-return]
        return field_of(data, number, f"entry '{record.id}' in subarchitecture '{record.subarchitecture}'")

    def decode(self, cls: builtins.type[M]) -> M:
        """The value as a ``cls`` message (a copy, as :meth:`cast.Component.get` gives)."""
        record = self._held()
        return decode(cls, record.type, record.data,
                      f"entry '{record.id}' in subarchitecture '{record.subarchitecture}'")

    def release(self, *_exc: object) -> None:
        """Give the value back; the views handed out end with it.

        BufferError, and the value still held, while something made from a
        view (a numpy array, another memoryview on it) is alive: drop those
        first. (It ends the ``with`` block too, which passes the exception.)
        """
        views, self._views = self._views, []
        for i, view in enumerate(views):
            try:
                view.release()
            except BufferError:
                self._views = views[i:]
                raise BufferError(
                    "an array or memoryview made from this view is still alive: drop it before releasing the view"
                ) from None
        self._record = None

    def __enter__(self) -> ValueView:
        return self

    __exit__ = release  # itself, not a function that calls it: one call fewer per block

    def __repr__(self) -> str:
        if self._record is None:
            return "ValueView(released)"
        r = self._record
        where = "shared memory" if r.shared is not None else "bytes"
        return f"ValueView({r.subarchitecture}/{r.id} type={r.type} v={r.version} {len(r.data)} bytes in {where})"

