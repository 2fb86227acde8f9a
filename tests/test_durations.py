"""The suite's own order (tests/durations.py): the longest files first, each file's tests in their order."""

from __future__ import annotations

import json
import re
import subprocess
import sys
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


def test_the_trees_run_leaves_to_the_compiled_run_its_tests_but_those_compiled_code_cannot_run() -> None:
    """make test's pytest on the tree with ``--compiled-run-has``: a test there runs in the compiled build's
    run instead, except one marked incompatible_with_mypyc (the compiled run leaves it out)."""
    target = "tests/core/test_metrics.py"
    out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", target,
                          "--compiled-run-has", target], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    kept = [line for line in out.stdout.splitlines() if line.startswith(f"{target}::")]
    assert kept == [f"{target}::test_a_report_value_that_is_not_a_number_is_refused_by_name"], out.stdout
    assert re.search(r"1/\d+ tests collected \(\d+ deselected\)", out.stdout), out.stdout
    wrong = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", target,
                            "--compiled-run-has", "tests/no_such_folder"], cwd=ROOT, capture_output=True, text=True,
                           timeout=120)
    assert wrong.returncode != 0 and "--compiled-run-has names no test folder or file" in wrong.stderr, wrong.stderr
