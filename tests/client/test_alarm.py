"""The dispatcher's alarm: set by one thread, slept on by another, on a timerfd or (where none) an Event."""

from __future__ import annotations

import os
import threading
import time
from types import ModuleType

import pytest

from cast.client import alarm
from cast.client.alarm import Alarm
from tests.client.native_build import INSTALLED, native_module


@pytest.fixture(scope="module")
def shared_native(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """cast.client._shared_native: the compiled build's, else built from its source."""
    return native_module("_shared_native", tmp_path_factory)[0]


@pytest.fixture(params=["c", "ctypes", "event"])
def timerfd(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch, shared_native: ModuleType) -> bool:
    """Whether the alarms made in the test use a timerfd, armed in C or through ctypes (else the Event fallback)."""
    monkeypatch.setattr(alarm, "_arm", shared_native.timerfd_arm if request.param == "c" else None)
    if request.param == "event":
        monkeypatch.setattr(alarm, "_libc_timerfd", lambda: None)
    return request.param != "event"


def test_the_compiled_build_arms_in_c() -> None:
    """The installed compiled build arms its alarms in C (an editable checkout has no C module: ctypes)."""
    assert (alarm._arm is not None) == INSTALLED
    if INSTALLED:
        assert Alarm()._arm is alarm._arm


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


def test_the_dispatchers_calls_set_and_cancel_as_the_methods_do(timerfd: bool) -> None:
    """setter() and canceller(), what the dispatcher calls around each callback, arm and disarm the same alarm."""
    a = Alarm()
    arm, disarm = a.setter(10), a.canceller()
    if not timerfd:  # the Event fallback's are its methods (its Event cannot be recalled: not tried here)
        assert disarm == a.cancel and arm.func == a.set and arm.args == (10,)  # type: ignore[attr-defined]
        a.close()
        return
    for _ in range(3):
        arm()
        disarm()
    woke = threading.Event()
    sleeper = threading.Thread(target=lambda: (a.wait(), woke.set()))
    sleeper.start()
    assert not woke.wait(0.3)  # disarmed: asleep
    a.setter(0.02)()
    sleeper.join(5)
    assert woke.is_set()
    a.close()


def test_timerfd_arm_refuses_what_is_no_descriptor_or_time(shared_native: ModuleType) -> None:
    """The C arm names what it refuses and arms nothing: a negative time, no descriptor, the wrong arguments."""
    a = Alarm()
    try:
        with pytest.raises(ValueError, match="ns 0 or more"):
            shared_native.timerfd_arm(a._fd, -1)
        with pytest.raises(ValueError, match="fd must be a descriptor"):
            shared_native.timerfd_arm(-1, 5)
        with pytest.raises(TypeError, match="2 arguments"):
            shared_native.timerfd_arm(a._fd)
        with pytest.raises(TypeError):
            shared_native.timerfd_arm(a._fd, 0.5)
        r, w = os.pipe()
        try:
            with pytest.raises(OSError):  # a descriptor that is no timerfd: EINVAL from the kernel
                shared_native.timerfd_arm(r, 1_000_000)
        finally:
            os.close(r)
            os.close(w)
    finally:
        a.close()
