"""Waiting for a condition in a test: a timeout, and a failure that says what was seen.

The timeout is a guard against a hang, not a measurement: a test that waits
asserts what happened, never how fast.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

__all__ = ["DEFAULT_TIMEOUT_S", "wait_for"]

T = TypeVar("T")

DEFAULT_TIMEOUT_S = 10.0
"""How long the kit waits when a test does not say (C++ and Java wait as long)."""

POLL_S = 0.01
"""How often a condition is asked again."""


def wait_for(condition: Callable[[], T], timeout: float = DEFAULT_TIMEOUT_S, what: str = "") -> T:
    """Ask ``condition()`` until it returns something true, and return that; fail after ``timeout`` seconds.

    The condition may also assert: an ``AssertionError`` it raises means "not
    yet", and its message is what a timeout reports, so a check written as
    assertions says what it last saw::

        wait_for(lambda: system.assert_entry("vision", "count", Int64Value, Int64Value(value=3)))

    Args:
        condition: asked every 10 ms, and once more when the time is up.
        timeout: seconds, a guard against a hang.
        what: what is awaited, for the failure message (default: the condition's name).

    Returns:
        The condition's first true answer.

    Raises:
        AssertionError: naming ``what`` and the timeout, with the condition's last answer, or the message
            of the last assertion it raised.

    """
    deadline = time.monotonic() + timeout
    while True:
        last_failure: AssertionError | None = None
        try:
            answer = condition()
        except AssertionError as failure:
            last_failure = failure
        else:
            if answer:
                return answer
        if time.monotonic() >= deadline:
            break
        time.sleep(POLL_S)
    name = getattr(condition, "__name__", "<lambda>")
    awaited = what or ("the condition" if name == "<lambda>" else f"{name}()")
    if last_failure is not None:
        raise AssertionError(f"timed out after {timeout:g} s waiting for {awaited}: {last_failure}") from None
    raise AssertionError(f"timed out after {timeout:g} s waiting for {awaited}; the condition last returned "
                         f"{answer!r}")
