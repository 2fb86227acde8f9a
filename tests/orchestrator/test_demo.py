"""The demo: `cast run configs/demo.yaml --for N` ends by itself, with its summary, exit 0."""

from __future__ import annotations

import asyncio
import io
import json
import os
import re
import subprocess
import threading
from pathlib import Path

import pytest
from rich.console import Console

from cast.config import load_config
from cast.orchestrator.orchestrator import Orchestrator, RunOptions
from cast.orchestrator.output import Output
from tests.orchestrator.conftest import CAST, wait_for


@pytest.mark.parametrize("sets", [[], ["--set", "SEGMENTER_LANGUAGE=python"]], ids=["default", "python-segmenter"])
def test_demo_runs_for_a_fixed_time_and_exits_zero(demo_built: Path, tmp_path: Path, sets: list[str]) -> None:
    summary = tmp_path / "summary.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    out = subprocess.run(
        [CAST, "run", str(demo_built), "--for", "6", "--runtime-dir", str(tmp_path / "rt"), "--summary-json",
         str(summary), *sets],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=180,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    text = out.stdout
    assert "cast: all 5 components connected in" in text
    assert "segmenter | frame 1: new region obj-1" in text
    assert "summary of scene-description" in text and "every component ran and stopped cleanly" in text
    assert "questions answered" in text  # the coordinator's stop() reports on the conversation
    data = json.loads(summary.read_text())
    assert data["failures"] == [] and data["system"] == "scene-description"
    sas = {sa["name"]: sa for sa in data["subarchitectures"]}
    assert set(sas) == {"vision", "language", "coordination"}
    assert sas["vision"]["types"].get("cast.examples.SceneObject", 0) >= 1
    assert sas["vision"]["counters"]["proposed"] >= 1
    assert {c["id"]: c["session"] for c in data["components"]} == dict.fromkeys(
        ["segmenter", "colour", "shape", "answerer", "coordinator"], "disconnected")
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
