"""The dispatcher's alarm: set by one thread, slept on by another, on a timerfd or (where none) an Event."""

from __future__ import annotations

import threading
import time

import pytest

from cast.client import alarm
from cast.client.alarm import Alarm


@pytest.fixture(params=[True, False], ids=["timerfd", "event"])
def timerfd(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> bool:
    """Whether the alarms made in the test use a timerfd (else libc's is hidden: the Event fallback)."""
    if not request.param:
        monkeypatch.setattr(alarm, "_libc_timerfd", lambda: None)
    return bool(request.param)


def test_the_sleeper_wakes_when_the_time_set_comes(timerfd: bool) -> None:
    a = Alarm()
    assert (a._event is None) == timerfd
    woke: list[float] = []
    sleeper = threading.Thread(target=lambda: (a.wait(), woke.append(time.monotonic())))
    sleeper.start()
    start = time.monotonic()
    if timerfd:
        a.set(10)  # replaced at once by a nearer time (the Event wakes the sleeper at each set: not tried there)
    a.set(0.05)
    sleeper.join(5)
    assert woke and woke[0] - start >= 0.045, woke
    a.set(0)  # at once
    begun = time.monotonic()
    a.wait()
    assert time.monotonic() - begun < 1
    a.close()


def test_a_cancelled_alarm_lets_the_sleeper_sleep_until_set_again(timerfd: bool) -> None:
    a = Alarm()
    assert (a._event is None) == timerfd
    for _ in range(3):  # the same time again and again, as the dispatcher sets it around each callback
        a.set(0.05)
        a.cancel()
    woke = threading.Event()
    sleeper = threading.Thread(target=lambda: (a.wait(), woke.set()))
    sleeper.start()
    if timerfd:  # the fallback's Event cannot be recalled: its sleeper wakes at a set and sleeps out the time
        assert not woke.wait(0.3)
    a.set(0.02)  # another time than the one kept
    sleeper.join(5)
    assert woke.is_set()
    a.close()
