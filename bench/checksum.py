"""The checksum every M8 watcher and subscriber computes over every byte it receives, and what it should be.

The sum of a value's little-endian 64-bit words modulo 2**64, a last partial
word as its bytes (``wordSum`` in ``cast_bench``, ``Bench.checksum`` in Java).
Computing it reads every byte, as a consumer of camera frames does; comparing
it with what the writer wrote shows that the bytes read were the frame's.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy

__all__ = ["MOD", "expected_cast", "expected_frames", "word_sum"]

MOD = 1 << 64


def word_sum(data: bytes | memoryview) -> int:
    """The checksum of ``data`` (read in place: numpy wraps the buffer without copying it)."""
    view = memoryview(data).cast("B")
    whole = len(view) // 8 * 8
    words = numpy.frombuffer(view[:whole], dtype="<u8")
    total = int(words.sum(dtype=numpy.uint64)) if whole else 0  # numpy's uint64 sum wraps modulo 2**64
    del words  # the array holds the buffer: dropped so that a lent view can be given back
    return (total + sum(view[whole:])) % MOD


def _ones(size: int) -> int:
    """The checksum of ``size`` bytes of 1."""
    return 0x0101010101010101 * (size // 8) + size % 8


def expected_cast(sent_order: Iterable[int], received: Iterable[int], size: int,
                  sizes: Mapping[int, int] | None = None) -> int:
    """What a CAST watcher's checksum must be, having received the overwrites ``received`` of ``sent_order``.

    The writers (bench/image_writer.py, ``image-write``) alternate values of
    ``size`` bytes (``sizes[revision]`` where given: M8's warm-up) of 1 and of
    2: the i-th overwrite (by revision) the ``i % 2``-th.
    """
    order = {revision: i for i, revision in enumerate(sorted(sent_order))}
    sizes = sizes or {}
    return sum((order[r] % 2 + 1) * _ones(sizes.get(r, size)) for r in received if r in order) % MOD


def expected_frames(received: Iterable[int], size: int, sizes: Mapping[int, int] | None = None) -> int:
    """What a peer subscriber's checksum must be, having received the frames numbered ``received``.

    A frame (bench.peer_fanout.frame) is its sequence number as the first
    word, then ``size - 8`` bytes of ``p`` (``sizes[seq] - 8`` where given: M8's warm-up).
    """
    sizes = sizes or {}
    word = int.from_bytes(b"p" * 8, "little")

    def padding(pad: int) -> int:
        return (pad // 8) * word + (pad % 8) * ord("p")

    return sum(seq + padding(sizes.get(seq, size) - 8) for seq in received) % MOD
