"""Entry versions that are never given twice, across crashes and restarts.

Within one run of a server an entry's versions count its writes: an ADD gives
the *floor*, every later write the previous version + 1 (a re-add after a
delete continues). The floor is what keeps a restart from handing a version
out again for a different value:

- a server that restores every write anyone could have seen (a journal in
  ``always`` or ``batch``, or ``none`` after a clean shutdown) keeps the
  floor it had, 0 for a new journal, so versions stay a count of writes;
- a server that may have lost writes others saw (memory only, or ``none``
  after a crash) starts at an *epoch floor*: its start time in microseconds
  since the Unix epoch. Every version such a server gives is at most the
  time, in microseconds, at which it gives it (:func:`check_outran`), so the
  next epoch floor, taken later, is above every version given before.

Microseconds keep versions below 2**53, so they stay exact in clients that
hold numbers as doubles (JavaScript), until the year 2255.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from cast.errors import ResourceExhaustedError

__all__ = ["check_outran", "epoch_floor", "next_version"]


def epoch_floor(clock_ns: Callable[[], int] = time.time_ns, above: int = -1) -> int:
    """The floor of a run that may follow lost writes: now in µs, and more than ``above``."""
    return max(clock_ns() // 1000, above + 1)


def next_version(previous: int | None, floor: int) -> int:
    """The version a write gives: ``previous + 1`` (0 for a new id), but never below ``floor``."""
    version = 0 if previous is None else previous + 1
    return version if version >= floor else floor


def check_outran(version: int, floor: int, now_ns: int, sa: str, entry_id: str) -> None:
    """RESOURCE_EXHAUSTED if an epoch-floored version would pass the clock (µs).

    Only servers with an epoch floor need this: it is what makes the next
    epoch floor safe. It needs one write per microsecond to one entry, on
    average since the server started, to trigger.
    """
    if floor and version > now_ns // 1000:
        raise ResourceExhaustedError(
            f"entry '{entry_id}' in subarchitecture '{sa}' would reach version {version}, past the server's "
            f"clock ({now_ns // 1000} µs): its versions carry the server's start time and may not outrun the "
            "clock, or a restart could give one twice; write it less often (at most once per microsecond) "
            "or retry in a moment"
        )
