"""Large values go back to the system when freed: glibc's mmap threshold, fixed for the server process.

glibc serves a large ``malloc`` (over 128 KiB) with its own ``mmap`` and unmaps
it on ``free``, until the first such block is freed: it then raises the
threshold to that block's size (up to 32 MiB), and from there on 1 MiB values
come from the heap, whose freed holes the process keeps. A server that
overwrites a 1 MiB image 30 times a second then grows to about three times
what its history holds (bench M8). Setting the threshold explicitly turns the
adjustment off, so each large value is mapped and unmapped with its lifetime;
an ``mmap`` of 1 MiB costs microseconds, far less than moving the value.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

__all__ = ["MMAP_THRESHOLD", "return_large_blocks"]

log = logging.getLogger("cast.server")

_M_MMAP_THRESHOLD = -3  # mallopt's parameter number in glibc's malloc.h
MMAP_THRESHOLD = 128 * 1024
"""Blocks at least this large are mapped on their own (glibc's initial value, kept fixed)."""


def return_large_blocks() -> bool:
    """Fix glibc's mmap threshold for this process; False where the C library is not glibc (nothing done)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 - only glibc has it; musl's mallopt does nothing useful
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    ok = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    if not ok:
        log.debug("mallopt(M_MMAP_THRESHOLD) refused; large values may stay in the heap")
    return ok
