"""Fixtures of the agent tests: one root, one `cast serve` for the components, one agent, per module."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.agent.harness import CONFIG, AgentHandle, make_root, start_agent
from tests.conftest import ServerHandle, serve


@pytest.fixture(scope="module")
def root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The agent's root: the configuration and the components module."""
    return make_root(tmp_path_factory.mktemp("agent-root"))


@pytest.fixture(scope="module")
def wm_server(root: Path) -> Iterator[ServerHandle]:
    """The working-memory server the launched components connect to."""
    handle = serve(root / CONFIG, cwd=root)
    yield handle
    handle.stop()


@pytest.fixture(scope="module")
def agent(root: Path) -> Iterator[AgentHandle]:
    """A `cast agent` trusting tokens signed with the test secret."""
    handle = start_agent(root)
    yield handle
    handle.stop()
