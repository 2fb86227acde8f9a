"""The suite's own order (tests/durations.py): the longest files first, each file's tests in their order."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests import durations
from tests.conftest import ROOT


@dataclass
class _Item:
    nodeid: str


def test_files_go_longest_first_and_keep_their_own_order(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(durations, "known_seconds", lambda: {"a.py": 1.0, "b.py": 100.0, "c.py": 10.0, "d.py": 5.0})
    items: list[Any] = [_Item(n) for n in ("a.py::x", "a.py::y", "new.py::z", "b.py::y", "b.py::x", "c.py::w")]
    durations.longest_files_first(items)
    # new.py has no record: it counts as the median file (10 s of 1, 5, 10, 100), so it ties with c.py and
    # keeps its place before it (ties keep the collection's order); a.py, the shortest, goes last.
    assert [i.nodeid for i in items] == ["b.py::y", "b.py::x", "new.py::z", "c.py::w", "a.py::x", "a.py::y"]


def test_the_last_run_on_the_machine_comes_before_the_committed_record(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    committed, last = tmp_path / "durations.json", tmp_path / "build" / "test-durations.json"
    committed.write_text(json.dumps({"a.py": 3}))
    monkeypatch.setattr(durations, "COMMITTED", committed)
    monkeypatch.setattr(durations, "LAST_RUN", last)
    assert durations.known_seconds() == {"a.py": 3.0}
    last.parent.mkdir()
    last.write_text("{not json")  # a run killed while writing it: the committed record still counts
    assert durations.known_seconds() == {"a.py": 3.0}
    last.write_text(json.dumps({"b.py": 4}))
    assert durations.known_seconds() == {"b.py": 4.0}


def test_the_committed_record_names_test_files_that_exist() -> None:
    record = json.loads(durations.COMMITTED.read_text())
    missing = [name for name in record if not (ROOT / name).is_file()]
    assert not missing, f"tests/durations.json names files that are gone: {missing}; copy build/test-durations.json"
    assert len(record) > 100
