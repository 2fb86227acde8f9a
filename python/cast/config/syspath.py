"""Temporarily importing from a configuration's ``python_path``."""

from __future__ import annotations

import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

__all__ = ["extended_sys_path"]


@contextmanager
def extended_sys_path(paths: Sequence[Path]) -> Iterator[None]:
    """Put ``paths`` first on ``sys.path`` for the duration (component and policy classes are imported there)."""
    added = [str(p) for p in paths if str(p) not in sys.path]
    sys.path[:0] = added
    try:
        yield
    finally:
        for p in added:
            if p in sys.path:
                sys.path.remove(p)
