"""Which tokens the orchestrator renews: only those of components whose process runs.

A component that exited gets no fresh token (so a token it leaked stops working within the ttl), and a
renewal that fails because the component ended while the call was under way is not reported as a
failure (it raced a normal exit or stop, as at the end of every run on several hosts).
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import pytest

from cast.auth import TokenSigner
from cast.config import parse_config
from cast.config.model import ComponentConfig
from cast.errors import CastError
from cast.orchestrator.security import LaunchSecurity

CONFIG = {
    "system": "renewal",
    "auth": {"token_ttl": 2},
    "hosts": {"arm": {"agent": "10.0.0.2:1"}},
    "servers": {"main": {"listen": "10.0.0.1:0", "subarchitectures": ["vision"]}},
    "subarchitectures": {"vision": {"components": {
        "here": {"class": "x:Here"},
        "there": {"class": "x:There", "host": "arm"},
    }}},
}


class Renewals:
    """The agent side of a renewal: records what it was sent; fails while ``failing`` (ending ``ends`` first)."""

    def __init__(self, state: dict[str, str]) -> None:
        self.state = state
        self.sent: list[str] = []
        self.failing = False
        self.ends = ""

    async def __call__(self, comp: ComponentConfig, token: str) -> None:
        self.sent.append(comp.id)
        if self.ends:
            self.state[self.ends] = "ended"
        if self.failing:
            raise CastError(f"NOT_FOUND: no process of component '{comp.id}' runs on this agent")


def _security(tmp_path: Path) -> tuple[LaunchSecurity, dict[str, str], Renewals]:
    config = parse_config(CONFIG)
    security = LaunchSecurity(config, TokenSigner(b"s" * 32), tmp_path)
    # "running", "stopping" or "ended", as the supervisor would say.
    state = {"here": "running", "there": "running"}
    security.runs = lambda cid, steady=False: state[cid] == "running" or (state[cid] == "stopping" and not steady)
    renewals = Renewals(state)
    security.remote = renewals
    for comp in config.components:
        security.contract(comp)
    return security, state, renewals


def test_only_running_components_get_fresh_tokens(tmp_path: Path) -> None:
    security, state, renewals = _security(tmp_path)
    here = tmp_path / "tokens" / "here.token"
    # A token file is replaced by a rename (a new inode), and tokens issued in the same second are equal.
    first = here.stat().st_ino
    asyncio.run(security.renew_all())
    assert here.stat().st_ino != first and renewals.sent == ["there"]

    state["here"] = state["there"] = "ended"
    ended = here.stat().st_ino
    asyncio.run(security.renew_all())
    assert here.stat().st_ino == ended, "a component that exited got a fresh token"
    assert renewals.sent == ["there"], "the agent was asked to renew a component that exited"


def test_a_component_being_stopped_keeps_getting_tokens(tmp_path: Path) -> None:
    security, state, renewals = _security(tmp_path)
    state["there"] = "stopping"
    asyncio.run(security.renew_all())
    assert renewals.sent == ["there"]


def test_a_renewal_that_raced_an_exit_is_not_reported(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    security, _, renewals = _security(tmp_path)
    renewals.failing, renewals.ends = True, "there"
    with caplog.at_level(logging.WARNING, logger="cast.orchestrator"):
        asyncio.run(security.renew_all())
    assert renewals.sent == ["there"] and not caplog.records, [r.getMessage() for r in caplog.records]


def test_a_renewal_that_fails_while_the_component_runs_is_reported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    security, _, renewals = _security(tmp_path)
    renewals.failing = True
    with caplog.at_level(logging.WARNING, logger="cast.orchestrator"):
        asyncio.run(security.renew_all())
    assert [r.getMessage() for r in caplog.records] == [
        "cannot renew the token of component 'there' on host 'arm': NOT_FOUND: no process of component 'there' "
        "runs on this agent"]
