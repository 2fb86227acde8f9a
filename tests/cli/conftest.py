"""A demo system running for the whole CLI test session."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.orchestrator.conftest import CastRun, build_examples, start_cast_run, wait_for


@pytest.fixture(scope="session")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[CastRun]:
    """`cast run configs/demo.yaml`, running until its first question is answered (and then until the end)."""
    config = build_examples()
    run = start_cast_run(tmp_path_factory.mktemp("demo"), config)
    run.cwd = ROOT  # the README's commands use paths relative to the repository
    try:
        wait_for(lambda: any(e["id"] == "question-1" and e["author"] == "answerer"
                             for e in run.cli_json("ls", "language")), what="the first answer")
        yield run
    finally:
        code = run.stop()
        assert code == 0, run.output()


@pytest.fixture
def repo() -> Path:
    return ROOT
