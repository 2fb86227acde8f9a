"""A launched component's first contact (cast.client.runner.LaunchContract.connect): which failures are
asked again, when the connect window ends, and what the runner then says; the same as the C++ and Java
runners' unit tests (connect_window_test.cc, ConnectWindowTest.java). Runs on a clock of its own: the
waits only move that clock forward.
"""

from __future__ import annotations

from typing import Any

import pytest

from cast.client import runner
from cast.errors import CastError, DeadlineExceededError, UnauthenticatedError, UnavailableError

CONTRACT = runner.LaunchContract("127.0.0.1:4711", "late", "vision", "tok.sig", {})


class FakeClock:
    """Stands still except when the code under test sleeps."""

    def __init__(self) -> None:
        self.now = 0.0
        self.waits: list[float] = []

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.waits.append(seconds)
        self.now += seconds


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    fake = FakeClock()
    monkeypatch.setattr(runner, "time", fake)
    return fake


def attempts(monkeypatch: pytest.MonkeyPatch, failures: list[CastError]) -> list[int]:
    """Make the transport fail with ``failures`` in order, then connect; the list counts the calls."""
    calls: list[int] = []

    def transport(*_args: Any, **_kw: Any) -> str:
        calls.append(1)
        if len(calls) <= len(failures):
            raise failures[len(calls) - 1]
        return "connected"

    monkeypatch.setattr(runner, "GrpcTransport", transport)
    return calls


def refused() -> UnavailableError:
    return UnavailableError("server unavailable (connection refused)")


def test_a_server_that_answers_late_is_asked_again_with_backoff(monkeypatch: pytest.MonkeyPatch,
                                                                clock: FakeClock) -> None:
    calls = attempts(monkeypatch, [refused(), DeadlineExceededError("Deadline Exceeded"), refused()])
    connected: Any = CONTRACT.connect()
    assert connected == "connected"
    assert len(calls) == 4
    assert len(clock.waits) == 3 and clock.waits[0] < clock.waits[2], clock.waits


def test_other_errors_fail_at_once(monkeypatch: pytest.MonkeyPatch, clock: FakeClock) -> None:
    calls = attempts(monkeypatch, [UnauthenticatedError("token signature does not match")])
    with pytest.raises(UnauthenticatedError):
        CONTRACT.connect()
    assert len(calls) == 1 and clock.waits == []


def test_gives_up_when_the_window_has_passed_saying_where_for_how_long_and_what_to_check(
    monkeypatch: pytest.MonkeyPatch, clock: FakeClock
) -> None:
    calls = attempts(monkeypatch, [refused()] * 1000)
    with pytest.raises(UnavailableError) as failed:
        CONTRACT.connect()
    assert failed.value.message == (
        "no CAST system answered at 127.0.0.1:4711 within 20 s (CAST_ENDPOINT, spoken to in plaintext): check that "
        "the system is running and that CAST_ENDPOINT and CAST_TLS_* are its address and TLS settings (last error: "
        "server unavailable (connection refused))"
    )
    assert 2 < len(calls) < 100, "asked again, with a backoff that grows"
    assert clock.now >= runner.CONNECT_WINDOW_S


def test_the_window_is_twenty_seconds_and_its_words_match_the_other_runners() -> None:
    assert runner.CONNECT_WINDOW_S == 20.0
    assert runner.CONNECT_RETRIED == ("UNAVAILABLE", "DEADLINE_EXCEEDED")
    said = runner.connect_gave_up("h:1", 1.5, True, refused())
    assert "within 1.5 s (CAST_ENDPOINT, spoken to with TLS)" in said


def test_cast_connect_window_s_sets_the_window_and_a_bad_value_is_named() -> None:
    env = {"CAST_ENDPOINT": "127.0.0.1:4711", "CAST_COMPONENT_ID": "late", "CAST_SUBARCHITECTURE": "vision",
           "CAST_TOKEN": "tok.sig"}
    assert runner.LaunchContract.from_env(env).connect_window == 20.0
    assert runner.LaunchContract.from_env({**env, "CAST_CONNECT_WINDOW_S": "2.5"}).connect_window == 2.5
    assert runner.LaunchContract.from_env({**env, "CAST_CONNECT_WINDOW_S": "0"}).connect_window == 0.0
    for bad in ("soon", "-1", "inf", "nan"):
        with pytest.raises(CastError, match=f"CAST_CONNECT_WINDOW_S '{bad}': give the seconds"):
            runner.LaunchContract.from_env({**env, "CAST_CONNECT_WINDOW_S": bad})
