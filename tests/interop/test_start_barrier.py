"""The start barrier across languages: watchers in Python, C++ and Java register in start(), writers in
all three write first thing in run(), and every watcher sees every write, run after run.

The components: tests/orchestrator/components/barrier_components.py (Python),
cpp_client/tests/components/cast_test_barrier.cc (C++, `writer` or `watcher` as its argument),
java_client/src/test/java/cast/itest/BarrierWriter.java and BarrierWatcher.java (Java). Each watcher
reports what it saw in an entry ``seen-<watcher>-<writer>`` = how many of the writer's entries came
before its ``-end`` entry.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from google.protobuf.wrappers_pb2 import Int64Value

from tests.conftest import wait_for
from tests.interop.cpp_support import cast_run, cpp_executable
from tests.interop.java_support import TEST_CLASSES, java_classpath
from tests.orchestrator.conftest import COMPONENTS
from tests.orchestrator.test_start_barrier import WRITES, seen

RUNS = 3


def _components(role: str) -> dict[str, dict[str, Any]]:
    """One component of ``role`` (writer or watcher) per language, ids ``w-<lang>`` / ``watch-<lang>``."""
    cls = "BarrierWriter" if role == "writer" else "BarrierWatcher"
    prefix = "w" if role == "writer" else "watch"
    return {
        f"{prefix}-py": {"class": f"barrier_components:{cls}"},
        # A command line with an argument is `language: other`; the C++ library still registers as cpp.
        f"{prefix}-cpp": {"language": "other", "run": [str(cpp_executable("cast_test_barrier")), role]},
        f"{prefix}-java": {"language": "java", "class": f"cast.itest.{cls}", "classpath": [str(TEST_CLASSES)]},
    }


@pytest.mark.parametrize("attempt", range(RUNS))
def test_watchers_in_three_languages_see_every_write_of_writers_in_three_languages(
    tmp_path: Path, attempt: int
) -> None:
    java_classpath()  # fails the test when the build is missing (cpp_executable too)
    writers = {cid: {**spec, "privileged": True, "args": {"sa": "b", "count": WRITES}}
               for cid, spec in _components("writer").items()}
    config = tmp_path / "barrier.yaml"
    config.write_text(yaml.safe_dump({
        "system": "barrier",
        "python_path": [str(COMPONENTS)],
        "subarchitectures": {"a": {"components": writers}, "b": {"components": _components("watcher")}},
    }, sort_keys=False))
    run = cast_run(config, tmp_path / "runtime")
    reader = None
    try:
        reader = run.act_as("reader", "b")
        pairs = {(w, src) for w in _components("watcher") for src in writers}

        def reports() -> dict[tuple[str, str], int]:
            return seen([(e.id, e.value.value) for e in reader.get_all(Int64Value) if e.id.startswith("seen-")])

        try:
            wait_for(lambda: pairs <= set(reports()), timeout=120, what="every watcher's report")
        except AssertionError:
            raise AssertionError(f"reports {reports()}; expected each of {sorted(pairs)}\n{run.output()}") from None
        assert reports() == {pair: WRITES for pair in pairs}, run.output()
        assert "all 6 components started in" in run.output()
    finally:
        if reader is not None:
            reader._cast_close()
        assert run.stop() == 0, run.output()
