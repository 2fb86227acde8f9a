"""Two systems measured in turns: CAST's writer in the even seconds, the peer's publisher in the odd ones.

The machines this project is measured on change speed by up to 2 x from one
15-second stretch to the next, for every process at once
(docs/performance-m8.md, "A and B in the same round"). Rounds of CAST
alternating with rounds of Zenoh therefore judge the minute as much as the
two systems. M8's judged phase instead runs both at once, every process of
both started and warmed up, and lets each write only in its own seconds of
``CLOCK_MONOTONIC``: CAST's C++ writer (``cast_bench image-write`` with a turn)
in the even ones, the peer's publisher (:func:`bench.peer_fanout.drive` with a
turn) in the odd ones. The two sides then share the machine's state to within
a second, and the other side's processes sleep while one side writes. M7
measures the write -> event latencies of its three client libraries the same
way, three sides taking a second each in turn.

A side writes in its seconds from :data:`SKIP_NS` after the second begins,
so that the other side's last frame is read before its first; its frames keep
their pace within a second and start again at that offset in its next one.
"""

from __future__ import annotations

import time

__all__ = ["CAST", "NONE", "PEER", "SKIP_NS", "in_turn", "next_start", "wait_for_turn"]

NONE, CAST, PEER = 0, 1, 2
"""No turn (write at any time), CAST's (the even seconds), the peer's (the odd ones): ``cast_bench``'s TURN too."""

SKIP_NS = 70_000_000
"""A side's first frame in a second comes this long after the second begins (two frames at 30 Hz)."""

SECOND_NS = 1_000_000_000


def in_turn(turn: int, ns: int, sides: int = 2) -> bool:
    """Whether CLOCK_MONOTONIC time ``ns`` is in ``turn``'s writing time (always, for NONE).

    Of ``sides`` sides taking turns, side ``turn`` (1 to ``sides``) writes in
    the seconds whose number modulo ``sides`` is ``turn - 1``: with two, CAST
    in the even ones and PEER in the odd ones.
    """
    if turn == NONE:
        return True
    return ns // SECOND_NS % sides == turn - 1 and ns % SECOND_NS >= SKIP_NS


def next_start(turn: int, ns: int, sides: int = 2) -> int:
    """The first moment at or after ``ns`` in ``turn``'s writing time."""
    if in_turn(turn, ns, sides):
        return ns
    second = ns // SECOND_NS
    return (second + (turn - 1 - second) % sides) * SECOND_NS + SKIP_NS


def wait_for_turn(turn: int, sides: int = 2) -> bool:
    """Sleep until ``turn``'s writing time; True if it slept (its pace starts again from now)."""
    now = time.monotonic_ns()
    start = next_start(turn, now, sides)
    if start == now:
        return False
    time.sleep((start - now) / 1e9)
    while time.monotonic_ns() < start:  # sleep may end a little early
        time.sleep(0.0002)
    return True
