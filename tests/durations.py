"""The suite's order: the test files that take longest first, so that the pytest workers end together.

`make test` hands whole files to two workers (``--dist loadfile``); a worker takes the next file when it
is free. A file that takes minutes (a C++ build, the benchmark smoke test) taken last keeps one worker busy
while the other has nothing left: the suite then lasts as long as that file's tail. Started first, such
files overlap the many short ones. The seconds per file come from the last run on this machine
(build/test-durations.json, written at the end of every run that ran the whole tests/ folder), else from
tests/durations.json (committed; refresh it by copying the former when files are added or change a lot).
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
COMMITTED = ROOT / "tests" / "durations.json"
LAST_RUN = ROOT / "build" / "test-durations.json"


def known_seconds() -> dict[str, float]:
    """Seconds per test file (path under the checkout), from the last run here or the committed file."""
    for path in (LAST_RUN, COMMITTED):
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(data, dict):
            return {str(k): float(v) for k, v in data.items()}
    return {}


def longest_files_first(items: list[pytest.Item]) -> None:
    """Order ``items`` by their file's known seconds, longest first; a file's own order is kept.

    A file with no record (new) counts as the median file, so it neither delays the long files nor
    comes last.
    """
    seconds = known_seconds()
    typical = sorted(seconds.values())[len(seconds) // 2] if seconds else 0.0
    # list.sort is stable: a file's tests, and files that tie, keep the collection's order.
    items.sort(key=lambda item: -seconds.get(_file(item.nodeid), typical))


def _file(nodeid: str) -> str:
    """The test file of a test id (``path::name[param]``), as the records name it."""
    return nodeid.split("::", 1)[0]


class Recorder:
    """Sums the seconds of every phase of every test per file, and writes them when the run covered tests/."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    def add(self, report: Any) -> None:
        """One phase's report (setup, call or teardown), on the process that reports (the xdist controller)."""
        self.seconds[_file(report.nodeid)] += float(getattr(report, "duration", 0.0))

    def write(self, session: pytest.Session) -> None:
        """build/test-durations.json, when the run was the whole suite and every test ran.

        Files the run left to the compiled build's run (``--compiled-run-has``) keep their last record.
        """
        args = [str(a) for a in session.config.args]
        whole = args in (["tests"], [str(ROOT / "tests")]) and not session.config.option.keyword \
            and not session.config.option.markexpr
        if not whole or session.testsfailed or not self.seconds:
            return
        seconds = dict(self.seconds)
        if session.config.getoption("compiled_run_has"):
            seconds = {**{f: s for f, s in known_seconds().items() if (ROOT / f).is_file()}, **seconds}
        LAST_RUN.parent.mkdir(exist_ok=True)
        LAST_RUN.write_text(json.dumps(dict(sorted(seconds.items(), key=lambda kv: -kv[1])), indent=0) + "\n")
