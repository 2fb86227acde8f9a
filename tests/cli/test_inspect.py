"""cast ls, get, watch, components, tasks against a running demo, as tables and as JSON."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

from cast.config import load_config
from tests.conftest import ROOT
from tests.orchestrator.conftest import CAST, CastRun

VISION_TYPE = "cast.examples.SceneObject"


def test_components_table_and_json(demo: CastRun) -> None:
    # Components that joined by hand (the README's visitor) may be listed too, after the configured ones.
    listed = demo.cli_json("components")
    rows = listed[:5]
    assert [r["id"] for r in rows] == ["segmenter", "colour", "shape", "answerer", "coordinator"]
    by_id = {r["id"]: r for r in rows}
    assert by_id["coordinator"]["privileged"] is True and by_id["colour"]["privileged"] is False
    assert {r["state"] for r in rows} == {"running"}
    languages = {c.id: c.language for c in load_config(ROOT / "configs" / "demo.yaml").components}
    assert {r["id"]: r["language"] for r in rows} == languages  # the segmenter may be the C++ one
    assert by_id["shape"]["kind"] == "managed"
    assert all(r["pid"] > 0 and r["sessions"] == 1 for r in rows)
    # Each client library (Python, C++, Java) registered with its release, the repository's VERSION.
    version = (ROOT / "VERSION").read_text().strip()
    assert {r["id"]: r["library_version"] for r in rows} == {r["id"]: version for r in rows}
    table = demo.cli("components").stdout
    # The five configured and any that joined by hand (the session's demo is shared by tests/cli's files).
    assert f"system 'scene-description': {len(listed)} components" in table, table
    assert re.search(r"coordinator\s*│\s*coordination\s*│\s*python\s*│\s*" + re.escape(version)
                     + r"\s*│\s*unmanaged\s*│\s*yes\s*│\s*running", table)


def test_ls_lists_entries_of_one_sa_or_all(demo: CastRun) -> None:
    vision = demo.cli_json("ls", "vision")
    objects = [e for e in vision if e["type"] == VISION_TYPE]
    assert objects and all(e["subarchitecture"] == "vision" for e in vision)
    assert {e["author"] for e in objects} <= {"segmenter", "colour", "shape"}
    assert set(vision[0]) == {"subarchitecture", "id", "type", "version", "author", "revision", "modified"}
    everything = demo.cli_json("ls")
    assert {e["subarchitecture"] for e in everything} >= {"vision", "language"}
    only = demo.cli_json("ls", "--type", "cast.examples.Question")
    assert only and {e["subarchitecture"] for e in only} == {"language"}
    table = demo.cli("ls", "language").stdout
    assert re.search(r"language\s*│\s*question-1\s*│\s*cast\.examples\.Question\s*│\s*\d+\s*│\s*answerer", table)


def test_get_renders_the_value_through_its_schema(demo: CastRun) -> None:
    entry = demo.cli_json("get", "language", "question-1")
    assert entry["type"] == "cast.examples.Question" and entry["id"] == "question-1"
    assert entry["value"]["text"] == "what is left of the red cube?"
    assert entry["value"]["answer"] == "the blue ball is just left of the red cube"
    assert entry["value"]["answered"] is True and entry["author"] == "answerer"
    text = demo.cli("get", "language", "question-1").stdout
    assert "language/question-1" in text and '"answer": "the blue ball is just left of the red cube"' in text


def test_get_and_ls_errors_name_what_is_wrong(demo: CastRun) -> None:
    out = demo.cli("get", "language", "no-such-entry", check=False)
    assert out.returncode == 2 and "no entry 'no-such-entry' in subarchitecture 'language'" in out.stderr
    out = demo.cli("ls", "visoin", check=False)
    assert out.returncode == 2
    assert "no subarchitecture 'visoin' (known: vision, language, coordination)" in out.stderr


def test_watch_prints_one_json_line_per_event(demo: CastRun) -> None:
    out = demo.cli("watch", "--sa", "language", "--from", "1", "--count", "4")
    events = [json.loads(line) for line in out.stdout.splitlines()]
    assert [e["revision"] for e in events] == [1, 2, 3, 4]
    assert events[0]["operation"] == "add" and events[0]["id"] == "question-1"
    assert events[0]["source_component"] == "coordinator" and events[0]["source_subarchitecture"] == "coordination"
    assert {e["subarchitecture"] for e in events} == {"language"}
    assert set(events[0]) == {"revision", "operation", "subarchitecture", "id", "type", "source_component",
                              "source_subarchitecture", "version", "time"}


def test_watch_filters_and_values(demo: CastRun) -> None:
    out = demo.cli("watch", "--sa", "language", "--from", "1", "--type", "cast.examples.Question",
                   "--op", "overwrite", "--values", "--count", "1")
    (event,) = [json.loads(line) for line in out.stdout.splitlines()]
    assert event["operation"] == "overwrite" and event["source_component"] == "answerer"
    assert event["value"]["answered"] is True
    # Task decisions are events too: the language TM's first task, adopted.
    out = demo.cli("watch", "--sa", "language", "--from", "1", "--type", "cast.v1.Task", "--op", "overwrite",
                   "--values", "--count", "1")
    (task,) = [json.loads(line) for line in out.stdout.splitlines()]
    assert task["source_component"] == "language.task_manager"
    assert task["value"]["state"] == "TASK_STATE_ADOPTED" and task["value"]["component"] == "answerer"


def test_tasks_counts_and_live_tasks(demo: CastRun) -> None:
    data = demo.cli_json("tasks")
    counters = {c["subarchitecture"]: c for c in data["subarchitectures"]}
    assert counters["vision"]["policy"] == "fifo(max_concurrent=2)"
    assert counters["language"]["policy"] == "priority(max_concurrent=1)"
    assert counters["vision"]["adopted"] >= 1 and counters["language"]["completed"] >= 1
    assert all(t["state"] in ("waiting", "adopted") for t in data["tasks"])
    one = demo.cli_json("tasks", "language")
    assert [c["subarchitecture"] for c in one["subarchitectures"]] == ["language"]
    table = demo.cli("tasks").stdout
    assert "task managers" in table and "live tasks" in table
    assert re.search(r"vision\s*│\s*fifo\(max_concurrent=2\)", table)


def test_inspection_without_a_running_system_says_so(demo: CastRun, tmp_path: Path) -> None:
    env = {k: v for k, v in demo.cli_environment().items() if k != "CAST_RUNTIME_DIR"}
    out = subprocess.run([CAST, "components"], cwd=str(tmp_path), env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2
    assert "no running system found" in out.stderr
