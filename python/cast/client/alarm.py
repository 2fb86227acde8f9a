"""A one-shot alarm one thread sets and another sleeps on, without waking the sleeper to set it.

The dispatcher's standby thread (cast.client.dispatcher) must look again
STANDBY_S after a callback begins, and callbacks begin at every event. Waking
the standby at each one (an ``Event``) to start its wait cost a context switch
and a turn of the GIL at the very moment the callback reads its event, and
another wake-up when that wait ended (docs/performance-m8.md, "The standby
thread's alarm").
A Linux timerfd is armed by the dispatcher with one system call when a callback
begins and disarmed with another when it returns, so the standby wakes only
for a callback that runs past the time set.

:class:`Alarm` uses ``os.timerfd_*`` (Python 3.13+) or, before that, libc's
``timerfd_create``/``timerfd_settime`` through ctypes; where neither exists it
falls back to an ``Event`` that wakes the sleeper at once, which then sleeps
until the time set (the older behaviour, correct, costlier). The compiled
build arms and disarms the timerfd in C (``cast.client._shared_native``):
through ctypes the arming took about 11 us of each event's path on a 30 Hz
watcher's cold caches (docs/performance-m8.md, "The Python watcher's own
path, step by step"), and :meth:`Alarm.setter` gives the dispatcher a call
with no Python frame in it.
"""

from __future__ import annotations

import ctypes
import functools
import os
import threading
import time
from collections.abc import Callable

from cast.client.shm_session import native_module

__all__ = ["Alarm"]

_CLOCK_MONOTONIC = 1
_TFD_CLOEXEC = 0o2000000


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _libc_timerfd() -> tuple[int, Callable[..., int]] | None:
    """A timerfd and libc's timerfd_settime, or None where libc has none."""
    try:
        # PyDLL: the calls keep the GIL (timerfd_settime never blocks), so arming does not invite a thread switch.
        libc = ctypes.PyDLL(None, use_errno=True)
        create, settime = libc.timerfd_create, libc.timerfd_settime
    except (OSError, AttributeError):
        return None
    create.argtypes, create.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # No argtypes for settime: converting through them was most of a call's cost (set and cancel run around every
    # callback), and its arguments are always two ints, a pointer made in this module and None (NULL).
    settime.restype = ctypes.c_int
    fd = create(_CLOCK_MONOTONIC, _TFD_CLOEXEC)
    return None if fd < 0 else (fd, settime)


def _native_arm() -> Callable[[int, int], None] | None:
    """The C ``timerfd_arm(fd, ns)`` where the build has it (cast.client.shm_session.native_module), else None."""
    native = native_module()
    return None if native is None else native.timerfd_arm


_arm = _native_arm()


class Alarm:
    """Armed by any thread (:meth:`set`), slept on by one (:meth:`wait`); closed once (:meth:`close`)."""

    def __init__(self) -> None:
        self._fd = -1
        self._settime: Callable[..., int] | None = None
        self._event: threading.Event | None = None
        self._due = 0.0  # the fallback's deadline (time.monotonic())
        # The last time set and its itimerspec, kept (never changed once made) because the dispatcher sets the same
        # time at every callback; replaced whole, so a thread setting another time never changes what one reads.
        self._spec: tuple[float, object] = (0.0, None)
        self._zero = ctypes.byref(_Itimerspec())  # all zero: disarmed
        self._arm: Callable[[int, int], None] | None = None  # C timerfd_arm(fd, ns): a timerfd, the compiled build
        if hasattr(os, "timerfd_create"):  # Python 3.13+
            self._fd = os.timerfd_create(time.CLOCK_MONOTONIC, flags=os.TFD_CLOEXEC)  # type: ignore[attr-defined]
        else:
            made = _libc_timerfd()
            if made is None:
                self._event = threading.Event()
                return
            self._fd, self._settime = made
        self._arm = _arm

    def setter(self, seconds: float) -> Callable[[], None]:
        """A call that does ``set(seconds)``: with the C arm one C call, no Python frame (the dispatcher's, each event).

        Like :meth:`canceller`'s call, it names the timerfd by its descriptor:
        not to be called once the alarm is closed.
        """
        arm = self._arm
        if arm is not None:
            return functools.partial(arm, self._fd, _nanoseconds(seconds))
        return functools.partial(self.set, seconds)

    def canceller(self) -> Callable[[], None]:
        """A call that does :meth:`cancel`: with the C arm one C call, no Python frame."""
        arm = self._arm
        if arm is not None:
            return functools.partial(arm, self._fd, 0)
        return self.cancel

    def set(self, seconds: float) -> None:
        """Wake the sleeper ``seconds`` from now (at once for 0 or less), replacing any earlier time."""
        seconds = max(seconds, 1e-9)  # 0 would disarm a timerfd
        if self._fd < 0 and self._event is None:
            return  # closed: its owner stopped
        if self._arm is not None:
            self._arm(self._fd, _nanoseconds(seconds))
            return
        if self._event is not None:
            self._due = time.monotonic() + seconds
            self._event.set()
        elif self._settime is not None:
            last, ref = self._spec
            if last != seconds:  # never at the first set: the time kept starts at 0, below any time set
                sec = int(seconds)
                ref = ctypes.byref(_Itimerspec(it_value=_Timespec(sec, int((seconds - sec) * 1e9) or 1)))
                self._spec = (seconds, ref)
            if self._settime(self._fd, 0, ref, None) != 0:
                raise OSError(ctypes.get_errno(), "timerfd_settime failed")
        else:
            os.timerfd_settime(self._fd, initial=seconds)  # type: ignore[attr-defined]

    def cancel(self) -> None:
        """Unset it: the sleeper sleeps on until the next :meth:`set` (the fallback's ``Event`` cannot be recalled)."""
        if self._event is not None or self._fd < 0:
            return
        if self._arm is not None:
            self._arm(self._fd, 0)
        elif self._settime is not None:
            if self._settime(self._fd, 0, self._zero, None) != 0:
                raise OSError(ctypes.get_errno(), "timerfd_settime failed")
        else:
            os.timerfd_settime(self._fd, initial=0)  # type: ignore[attr-defined]

    def wait(self) -> None:
        """Sleep until the time set comes (returns at once if it came since the last wait)."""
        if self._event is None:
            try:
                os.read(self._fd, 8)
            except OSError:  # closed meanwhile: the owner is stopping
                pass
            return
        self._event.wait()
        self._event.clear()
        left = self._due - time.monotonic()
        if left > 0:
            time.sleep(left)

    def close(self) -> None:
        """Release the timer (the sleeper must have ended)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def _nanoseconds(seconds: float) -> int:
    """``seconds`` as a timerfd's nanoseconds: at least 1, since 0 would disarm it."""
    return max(1, int(seconds * 1e9))
