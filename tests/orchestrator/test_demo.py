"""The demo: `cast run configs/demo.yaml --for N` ends by itself, with its summary, exit 0."""

from __future__ import annotations

import asyncio
import io
import json
import os
import re
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from cast.config import load_config
from cast.orchestrator.orchestrator import Orchestrator, RunOptions
from cast.orchestrator.output import Output
from tests.conftest import ROOT
from tests.interop.cpp_support import cpp_executable
from tests.interop.java_support import java_classpath
from tests.orchestrator.conftest import CAST, CastRun, start_cast_run, wait_for

DEMO_JAR = ROOT / "examples" / "java-demo" / "target" / "cast-demo.jar"


def demo_builds() -> None:
    """The default demo's C++ segmenter and Java colour recogniser are built (`make test` builds them first).

    A missing build fails the test, it never skips it.
    """
    cpp_executable("segmenter")
    java_classpath()
    if not DEMO_JAR.is_file():
        pytest.fail(f"the demo's Java components are not built ({DEMO_JAR} missing): run `make java-demo` first")


def true_colours() -> dict[str, str]:
    """The colour of each object on the demo's table, and Python's colour namer (cast_examples.scene)."""
    sys.path.insert(0, str(ROOT / "examples" / "python"))
    try:
        from cast_examples.scene import make_scene
    finally:
        sys.path.pop(0)
    return {o.label: o.colour for o in make_scene(6, 7)}


@pytest.mark.parametrize(("sets", "languages"), [
    ([], {"segmenter": "cpp", "colour": "java"}),  # the default: components in all three languages
    (["--set", "SEGMENTER_LANGUAGE=python", "--set", "COLOUR_LANGUAGE=python"], {}),
], ids=["default", "all-python"])
def test_demo_runs_for_a_fixed_time_and_exits_zero(demo_built: Path, tmp_path: Path, sets: list[str],
                                                   languages: dict[str, str]) -> None:
    if languages:
        demo_builds()
    summary = tmp_path / "summary.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    out = subprocess.run(
        [CAST, "run", str(demo_built), "--for", "6", "--runtime-dir", str(tmp_path / "rt"), "--summary-json",
         str(summary), *sets],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=180,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    text = out.stdout
    assert "cast: all 5 components started in" in text
    assert "segmenter | frame 1: new region obj-1" in text
    assert "summary of scene-description" in text and "every component ran and stopped cleanly" in text
    assert "┃ SA " in text and "│ vision " in text  # the summary's cells padded from the table's edges too
    assert "questions answered" in text  # the coordinator's stop() reports on the conversation
    data = json.loads(summary.read_text())
    # Its outcomes for experiments: one report per answer it printed (the times are measured, never asserted).
    answers = len(re.findall(r"coordinator \| q\d+ .* -> ", text))
    reported = data["metrics"]["reports"].get("coordinator", {})
    if answers:
        assert reported["questions_answered"]["count"] == reported["questions_answered"]["sum"] == answers, reported
        assert reported["answer_time_s"]["count"] == answers and reported["answer_time_s"]["min"] >= 0, reported
    else:
        assert reported == {}, reported
    assert data["failures"] == [] and data["system"] == "scene-description"
    sas = {sa["name"]: sa for sa in data["subarchitectures"]}
    assert set(sas) == {"vision", "language", "coordination"}
    assert sas["vision"]["types"].get("cast.examples.SceneObject", 0) >= 1
    assert sas["vision"]["counters"]["proposed"] >= 1
    assert {c["id"]: c["session"] for c in data["components"]} == dict.fromkeys(
        ["segmenter", "colour", "shape", "answerer", "coordinator"], "disconnected")
    assert {c["id"]: c["language"] for c in data["components"]} == {
        **dict.fromkeys(["segmenter", "colour", "shape", "answerer", "coordinator"], "python"), **languages}
    assert sorted(p.name for p in (tmp_path / "rt" / "logs").iterdir()) == [
        "answerer.log", "colour.log", "coordinator.log", "segmenter.log", "shape.log"]


def test_live_status_view_on_a_terminal(demo_built: Path, tmp_path: Path) -> None:
    buffer = io.StringIO()
    console = Console(file=buffer, force_terminal=True, width=160, highlight=False)
    orch = Orchestrator(load_config(demo_built), RunOptions(runtime_dir=tmp_path / "rt", status_interval=0.05),
                        Output(console, live_status=True), dict(os.environ))
    thread = threading.Thread(target=lambda: asyncio.run(orch.run()), daemon=True)
    thread.start()
    try:
        wait_for(orch.connected.is_set, what="the demo to connect")
        wait_for(lambda: "events/s" in buffer.getvalue() and "coordinator" in buffer.getvalue(), what="the view")
    finally:
        orch.request_stop()
        thread.join(60)
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", buffer.getvalue())  # without the terminal's colours
    for column in ("components", "subarchitectures", "session", "restarts", "waiting", "running", "rejected"):
        assert column in text
    assert "summary of scene-description" in text


def vision_events(run: CastRun) -> list[dict[str, Any]]:
    """Every change of the vision WM so far, with values (`cast watch` from revision 1)."""
    out = run.cli("watch", "--sa", "vision", "--from", "1", "--values", "--for", "0.5")
    return [json.loads(line) for line in out.stdout.splitlines() if line.strip()]


def coloured(events: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per region label, the first write that gave it a colour."""
    first: dict[str, dict[str, Any]] = {}
    for e in events:
        if e["type"] == "cast.examples.SceneObject" and e["value"].get("colour"):
            first.setdefault(e["value"]["label"], e)
    return first


def completed_colour_tasks(events: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The colour tasks that ended, by task id."""
    return {e["value"]["task_id"]: e["value"] for e in events if e["type"] == "cast.v1.Task"
            and e["value"]["name"].startswith("colour ") and e["value"]["state"] == "TASK_STATE_COMPLETED"}


def all_coloured(events: list[dict[str, Any]]) -> list[dict[str, Any]] | None:
    """The events, once all six regions were added and each got its colour and its colour task ended (or was
    taken away first)."""
    regions = [e for e in events if e["type"] == "cast.examples.SceneObject"]
    added = {e["id"] for e in regions if e["operation"] == "add"}
    gone = {e["id"] for e in regions if e["operation"] == "delete"}
    done = {e["id"] for e in coloured(events).values()}
    ended = {t["data"]["object_id"] for t in completed_colour_tasks(events).values()}
    return events if len(added) == 6 and added <= (done & ended) | gone else None


@pytest.mark.parametrize("language", ["java", "python"])
def test_colour_recogniser_adopts_completes_and_refines(demo_built: Path, tmp_path: Path, language: str) -> None:
    """The colour tasks are the colour recogniser's, Java (the default) or Python: proposed, adopted,
    completed, and every region's colour written by it, the colour Python's namer gives."""
    demo_builds()
    summary = tmp_path / "summary.json"
    sets = [] if language == "java" else ["--set", "COLOUR_LANGUAGE=python"]
    run = start_cast_run(tmp_path, demo_built, "--summary-json", str(summary), *sets)
    truth = true_colours()
    try:
        events = wait_for(lambda: all_coloured(vision_events(run)), timeout=45, what="every region to get its colour")
    finally:
        code = run.stop()
    assert code == 0, run.output()
    wait_for(lambda: "summary of scene-description" in run.output(), what="the summary")  # all output read

    # Every region got its colour from the colour recogniser, the one Python's namer gives for its RGB.
    sys.path.insert(0, str(ROOT / "examples" / "python"))
    try:
        from cast_examples.scene import name_colour
    finally:
        sys.path.pop(0)
    assert len(coloured(events)) >= 5  # the segmenter takes one region away after 80 frames (13 s)
    for label, event in coloured(events).items():
        value = event["value"]
        assert event["source_component"] == "colour" and event["operation"] == "overwrite", event
        assert value["colour"] == truth[label] == name_colour(value["red"], value["green"], value["blue"]), event

    # The colour tasks: the colour recogniser's, adopted by the vision TM, completed as succeeded with the name.
    tasks = [e["value"] for e in events if e["type"] == "cast.v1.Task" and e["value"]["name"].startswith("colour ")]
    assert tasks and all(t["component"] == "colour" and t["data"]["feature"] == "colour" for t in tasks)
    assert any(t["state"] == "TASK_STATE_ADOPTED" for t in tasks)
    completed = {i: t for i, t in completed_colour_tasks(events).items() if t["outcome"] == "TASK_OUTCOME_SUCCEEDED"}
    assert {t["data"]["object_id"] for t in completed.values()} == {e["id"] for e in coloured(events).values()}
    assert all(t["reason"] in truth.values() for t in completed.values())

    # Its output, the same lines in either language: "obj-3 is red (task-7, 0.3 s)".
    said = re.findall(r"^\s*colour \| (obj-\d) is (\w+) \((task-\d+), \d+\.\d s\)$", run.output(), re.M)
    assert {(label, colour) for label, colour, _ in said} == {(label, truth[label]) for label in coloured(events)}
    assert {task for _, _, task in said} <= set(completed)

    data = json.loads(summary.read_text())
    assert data["failures"] == []
    colour = next(c for c in data["components"] if c["id"] == "colour")
    assert colour["language"] == language and colour["kind"] == "managed" and colour["sessions"] == 1
