"""The server's shared memory: segments of memory files that only the server writes, and the values placed in them.

A *segment* is a memory file (``memfd_create``, so it has no name in any file
system and nothing is left in ``/dev/shm`` whatever happens) that the server
maps read-write and then seals: ``F_SEAL_FUTURE_WRITE`` (from then on nobody,
the server included, may map it writable or ``write()`` to it; the server's
own mapping, made before the seal, stays writable), ``F_SEAL_GROW`` and
``F_SEAL_SHRINK`` (its size is fixed, so no reader's mapping can lose pages)
and ``F_SEAL_SEAL``. Readers get its descriptor and map it read-only.

A value is copied into a free extent of a segment (page-aligned) before its
write is applied, so what a writer does afterwards cannot change it. Within
its extent it starts where the bytes of its largest top-level ``bytes`` field
(an image's pixels) fall on a multiple of :data:`ALIGN`, so that a reader's
array over them is aligned (numpy's ``aligned`` flag; SIMD loads). The
extent is reused only once nothing holds the value: no record (an entry, the
history, a journal batch, an in-process reader: :class:`Placed` is freed with
the last of them) and no lease (a reader in another process that was sent it
and has not given it back). Pages of a segment are reused, not returned: a
fresh page costs far more than a reused one (docs/decisions.md, "Large values
by shared memory"); of the segments left empty, one is kept while values keep
coming (a *spare*, its pages faulted in already, so the next segment needed
costs nothing to make; :meth:`Arena.retire_empty`), the others are retired, and a retired segment's memory
goes back to the system once every reader has unmapped it.
"""

from __future__ import annotations

import bisect
import collections
import ctypes
import fcntl
import mmap
import os
import threading
import time
from collections.abc import Callable, Iterator

from cast.core.large_fields import largest_payload

__all__ = ["ALIGN", "PAGE", "SPARE_IDLE_S", "Arena", "Extents", "Placed", "Segment", "memory_file"]

PAGE = 4096
"""Extents start on a page: a reader may map one alone."""
ALIGN = 64
"""A value's largest ``bytes`` field starts on a multiple of this (a cache line; what AVX-512 loads want)."""

F_SEAL_FUTURE_WRITE = 0x0010  # Linux 5.1; Python's fcntl module does not name it
MFD_NOEXEC_SEAL = 0x0008  # Linux 6.3: a memory file that can never be executed
MADV_POPULATE_WRITE = 23  # Linux 5.14: fault pages in, writable, without changing what they hold
_POPULATE_STEP = 1 << 20  # one madvise at a time
SPARE_IDLE_S = 10.0
"""An emptied segment stays as a spare until no value was placed for this long (the writers stopped)."""


def _load_madvise() -> Callable[[int, int, int], int] | None:
    """The C library's ``madvise``, called through ctypes, which lets the GIL go during the call.

    ``mmap.madvise`` holds the GIL for as long as the kernel takes: faulting in
    1 MiB of fresh pages takes milliseconds, and the server's event loop would
    stop that long for every MiB of a new segment.
    """
    try:
        madvise = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return None
    madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
    madvise.restype = ctypes.c_int
    return madvise


_MADVISE = _load_madvise()


def memory_file(name: str, size: int) -> int:
    """A new memory file of ``size`` bytes that may be sealed (close-on-exec; not executable where the kernel knows)."""
    flags = os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING
    try:
        fd = os.memfd_create(name, flags | MFD_NOEXEC_SEAL)
    except OSError:  # an older kernel: the flag is unknown
        fd = os.memfd_create(name, flags)
    try:
        os.ftruncate(fd, size)
    except BaseException:
        os.close(fd)
        raise
    return fd


def round_up(size: int) -> int:
    """``size`` rounded up to whole pages (at least one)."""
    return max(PAGE, (size + PAGE - 1) // PAGE * PAGE)


class Extents:
    """First-fit allocation of page-aligned extents in ``[0, size)``; not thread-safe.

    Free space is a sorted list of (offset, size) runs, merged on free. The
    number of values alive at once is small (hundreds), so the linear scan is
    cheap next to copying a value.
    """

    __slots__ = ("_free", "size", "used")

    def __init__(self, size: int) -> None:
        self.size = size
        self.used = 0
        self._free: list[tuple[int, int]] = [(0, size)] if size else []

    def take(self, size: int) -> int | None:
        """The offset of a free extent of ``size`` bytes (whole pages), or None when none is left."""
        for i, (offset, run) in enumerate(self._free):
            if run >= size:
                if run == size:
                    del self._free[i]
                else:
                    self._free[i] = (offset + size, run - size)
                self.used += size
                return offset
        return None

    def give(self, offset: int, size: int) -> None:
        """Free the extent at ``offset`` (as :meth:`take` gave it), merging it with its neighbours."""
        self.used -= size
        free = self._free
        i = bisect.bisect_left(free, (offset, 0))
        if i and free[i - 1][0] + free[i - 1][1] == offset:
            i -= 1
            offset, size = free[i][0], free[i][1] + size
            del free[i]
        if i < len(free) and offset + size == free[i][0]:
            size += free[i][1]
            del free[i]
        free.insert(i, (offset, size))

    @property
    def empty(self) -> bool:
        """Whether nothing is allocated."""
        return self.used == 0


def _populate(madvise: Callable[[int, int, int], int], held: list[ctypes.c_char], size: int) -> None:
    """:meth:`Segment.populate`'s thread (a module function, not a closure: mypyc)."""
    try:
        base = ctypes.addressof(held[0])
        for start in range(0, size, _POPULATE_STEP):
            if madvise(base + start, min(_POPULATE_STEP, size - start), MADV_POPULATE_WRITE) != 0:
                return  # an older kernel: pages come on use
    finally:
        held.clear()


class Segment:
    """One sealed memory file of the arena and the server's writable mapping of it."""

    __slots__ = ("extents", "fd", "id", "map", "size", "view")

    def __init__(self, segment_id: int, size: int) -> None:
        self.id = segment_id
        self.size = size
        self.fd = memory_file(f"cast-arena-{segment_id}", size)
        try:
            # Mapped before the seal: F_SEAL_FUTURE_WRITE leaves this mapping writable and refuses every later one.
            self.map = mmap.mmap(self.fd, size)
            fcntl.fcntl(self.fd, fcntl.F_ADD_SEALS,
                        F_SEAL_FUTURE_WRITE | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_SEAL)
        except BaseException:
            os.close(self.fd)
            raise
        self.view = memoryview(self.map)
        self.extents = Extents(size)

    def populate(self) -> None:
        """Fault every page in now, on a thread of its own, so that no value's copy pays for fresh pages.

        A fresh page costs far more than a reused one (about 3 us here, docs/decisions.md): without
        this the first pass of values through a segment costs ~1 ms per MiB in the server's loop.
        ``MADV_POPULATE_WRITE`` leaves the bytes as they are, so copies may go on meanwhile; it is
        called with the GIL let go (:func:`_load_madvise`), so the server's loop goes on too.
        """
        madvise = _MADVISE
        if madvise is None:
            return
        try:
            # The thread's hold on the mapping: close() cannot unmap it meanwhile (BufferError: retried later).
            held = [ctypes.c_char.from_buffer(self.map)]
        except (TypeError, ValueError, BufferError):  # closed already
            return

        threading.Thread(target=_populate, args=(madvise, held, self.size), name=f"cast-arena-{self.id}",
                         daemon=True).start()

    def close(self) -> bool:
        """Unmap and close; False (nothing done) while something still holds a view of it."""
        try:
            self.view.release()
            self.map.close()
        except BufferError:
            self.view = memoryview(self.map)
            return False
        os.close(self.fd)
        return True


class _Extent:
    """Where one value is, and what still holds it: records (through :class:`Placed`) and leases."""

    __slots__ = ("held", "leases", "length", "offset", "segment", "size", "start", "value_id")

    def __init__(self, value_id: int, segment: Segment, offset: int, size: int, length: int, skew: int) -> None:
        self.value_id = value_id
        self.segment = segment
        self.offset = offset  # the extent's
        self.start = offset + skew  # the value's first byte
        self.size = size  # whole pages taken
        self.length = length  # the value's bytes
        self.held = True  # a Placed still refers to it
        self.leases = 0  # readers in other processes that were sent it and have not given it back


class Placed:
    """A value in the arena, as records hold it: its bytes (:attr:`view`, read-only) and where they are.

    Freed with the last reference to it (CPython frees at once): the extent is
    then reused, unless a reader still holds a lease on it.
    """

    __slots__ = ("__weakref__", "_arena", "_extent", "view")

    def __init__(self, arena: Arena, extent: _Extent) -> None:
        self._arena = arena
        self._extent = extent
        segment = extent.segment
        self.view = segment.view[extent.start: extent.start + extent.length].toreadonly()

    @property
    def value_id(self) -> int:
        """The value's id (in leases and RELEASE frames)."""
        return self._extent.value_id

    @property
    def segment(self) -> int:
        """The id of the segment holding it."""
        return self._extent.segment.id

    @property
    def offset(self) -> int:
        """Its first byte's offset in the segment."""
        return self._extent.start

    @property
    def length(self) -> int:
        """Its size in bytes."""
        return self._extent.length

    def __del__(self) -> None:
        # May run on any thread, inside any code: only queue the extent; the arena frees it at its next call.
        self._arena._dropped.append(self._extent)


class Arena:
    """The segments of the server's shared memory, at most ``max_bytes`` of them; thread-safe."""

    def __init__(self, max_bytes: int, segment_bytes: int) -> None:
        self.segment_bytes = round_up(segment_bytes)
        self.max_segments = max(1, max_bytes // self.segment_bytes)
        self._lock = threading.Lock()
        self._segments: dict[int, Segment] = {}
        self._next_segment = 1
        self._next_value = 1
        self._values: dict[int, _Extent] = {}  # every extent in use, by value id
        # Extents whose Placed was freed (appended from __del__, on any thread; deque appends are atomic).
        self._dropped: collections.deque[_Extent] = collections.deque()
        self.retired: list[Segment] = []  # retired, still mapped by the server until nothing holds a view
        self._last_put = -SPARE_IDLE_S  # time.monotonic() of the last value placed

    # ------------------------------------------------------------- values

    def put(self, data: memoryview | bytes) -> Placed | None:
        """A copy of ``data`` in the arena, or None when it is full (``max_bytes`` in use or held).

        Placed :data:`ALIGN`-aligned at its largest ``bytes`` field's first byte
        (:func:`cast.core.large_fields.largest_payload`; the value itself when it has none).
        """
        length = len(data)
        skew = -largest_payload(data) % ALIGN
        size = round_up(length + skew)
        with self._lock:
            self._collect()
            found = self._find(size)
            if found is None:
                return None
            segment, offset = found
            self._last_put = time.monotonic()
            extent = _Extent(self._next_value, segment, offset, size, length, skew)
            self._next_value += 1
            self._values[extent.value_id] = extent
        # The copy runs outside the lock: the extent is this call's alone until it returns.
        segment.view[extent.start: extent.start + length] = data
        return Placed(self, extent)

    def _find(self, size: int) -> tuple[Segment, int] | None:
        for segment in self._segments.values():
            offset = segment.extents.take(size)
            if offset is not None:
                return segment, offset
        if len(self._segments) >= self.max_segments or size > self.segment_bytes:
            return None
        segment = Segment(self._next_segment, self.segment_bytes)
        segment.populate()
        self._next_segment += 1
        self._segments[segment.id] = segment
        offset = segment.extents.take(size)
        assert offset is not None
        return segment, offset

    def lease(self, placed: Placed) -> None:
        """Count one more lease of ``placed`` (a reader in another process was sent it)."""
        with self._lock:
            placed._extent.leases += 1

    def give_back(self, value_ids: Iterator[int] | list[int]) -> int:
        """End one lease of each value named; the bytes of the leases ended (unknown ids are ignored)."""
        freed = 0
        with self._lock:
            for value_id in value_ids:
                extent = self._values.get(value_id)
                if extent is None or extent.leases <= 0:
                    continue
                extent.leases -= 1
                freed += extent.length
                if not extent.leases and not extent.held:
                    self._free(extent)
            self._collect()
        return freed

    def length_of(self, value_id: int) -> int:
        """The size of a value in use (0 if none)."""
        extent = self._values.get(value_id)
        return extent.length if extent is not None else 0

    def _collect(self) -> None:
        dropped = self._dropped
        while dropped:
            extent = dropped.popleft()
            extent.held = False
            if not extent.leases:
                self._free(extent)

    def _free(self, extent: _Extent) -> None:
        del self._values[extent.value_id]
        extent.segment.extents.give(extent.offset, extent.size)

    # ----------------------------------------------------------- segments

    def segment(self, segment_id: int) -> Segment | None:
        """A live segment by id."""
        return self._segments.get(segment_id)

    def retire_empty(self, now: float | None = None) -> list[int]:
        """Retire the segments left empty but one; their ids.

        One empty segment stays: the only one when every segment is empty
        (kept for the next value), and otherwise a *spare* while values keep
        coming (one was placed in the last :data:`SPARE_IDLE_S` before ``now``,
        ``time.monotonic()`` by default), so that the next segment the values
        need is one whose pages are faulted in already (making one costs ~60
        ms of CPU per 64 MiB, docs/performance-m8.md, "The write alone"). At most one spare is
        kept, it counts in ``segments`` like any other, and once the values
        stop it is retired too. A retired segment takes no more values; the
        server closes it once it holds no view of it, and its memory goes back
        to the system when every reader has unmapped it too (they are told by
        the caller).
        """
        with self._lock:
            self._collect()
            empty = [s for s in self._segments.values() if s.extents.empty]
            now = time.monotonic() if now is None else now
            if len(empty) == len(self._segments) or now - self._last_put < SPARE_IDLE_S:
                empty = empty[1:]
            for segment in empty:
                del self._segments[segment.id]
                self.retired.append(segment)
            self.retired = [s for s in self.retired if not s.close()]
        return [s.id for s in empty]

    def close(self) -> None:
        """Close every segment nothing holds a view of (the server is stopping)."""
        with self._lock:
            self._collect()
            self.retired.extend(self._segments.values())
            self._segments.clear()
            self.retired = [s for s in self.retired if not s.close()]

    def stats(self) -> dict[str, int]:
        """Segments and their bytes, values in use and their bytes, bytes lent to readers."""
        with self._lock:
            self._collect()
            return {
                "segments": len(self._segments),
                "segment_bytes": sum(s.size for s in self._segments.values()),
                "values": len(self._values),
                "value_bytes": sum(e.length for e in self._values.values()),
                "lent_bytes": sum(e.length * e.leases for e in self._values.values()),
            }
