"""A benchmark's working directory: removed after a run that ended, kept and named after one that failed."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.harness import scratch


def test_a_run_that_ends_removes_its_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    with scratch("cast-bench-t-") as work:
        (work / "server.log").write_text("up")
    assert not work.exists()


def test_a_run_that_fails_keeps_its_directory_and_names_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))
    with pytest.raises(RuntimeError), scratch("cast-bench-t-") as work:
        (work / "server.log").write_text("up")
        raise RuntimeError("the row failed")
    assert (work / "server.log").read_text() == "up"
    assert str(work) in capsys.readouterr().err
