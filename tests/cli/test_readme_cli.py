"""The README's sections on configuration, `cast run`, `cast token` and the inspection commands, run as written."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from cast.config import read_config
from tests.conftest import ROOT
from tests.orchestrator.conftest import CastRun, build_examples
from tests.test_readme import blocks, section

BIN = str(Path(sys.executable).parent)


def shell(script: str, env: dict[str, str], timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = {**env, "PATH": f"{BIN}{os.pathsep}{env.get('PATH', '')}"}
    return subprocess.run(["bash", "-c", "set -e\n" + script], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_configuration_example_is_valid(tmp_path: Path) -> None:
    (yaml_block,) = blocks(section("Configuration"), "yaml")
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "segmenter-python.yaml").write_text((ROOT / "configs/demo/segmenter-python.yaml").read_text())
    path = tmp_path / "example.yaml"
    path.write_text(yaml_block)
    config, problems = read_config(path, environ={})
    assert config is not None and not problems.items, [str(p) for p in problems.items]
    assert [c.id for c in config.components] == ["segmenter", "shape", "coordinator"]
    coordinator = config.component("coordinator")
    assert coordinator is not None and coordinator.restart.max_restarts == 3
    # The error shown is the one `cast check` gives for that mistake.
    (shown,) = blocks(section("Configuration"), "text")
    broken = tmp_path / "configs" / "broken.yaml"
    broken.parent.mkdir()
    broken.write_text("subarchitectures:\n  vision:\n    components:\n      x: {clas: a:B}\n")
    out = subprocess.run([f"{BIN}/cast", "check", "configs/broken.yaml"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 1 and shown.strip() in out.stderr


def test_running_commands(tmp_path: Path) -> None:
    build_examples()
    check, run = blocks(section("Running a system: `cast check`, `cast run`"), "sh")[0].strip().splitlines()
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    env["CAST_RUNTIME_DIR"] = str(tmp_path / "runtime")
    out = shell(check, env)
    assert out.returncode == 0 and "configs/demo.yaml: ok: system 'scene-description'" in out.stdout
    assert run == "cast run configs/demo.yaml --for 20"
    out = shell(run.replace("--for 20", "--for 2"), env, timeout=180)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "all 5 components started in" in out.stdout and "summary of scene-description" in out.stdout


def test_joining_commands(demo: CastRun) -> None:
    lines = blocks(section("Joining a running system: `cast token`"), "sh")[0].strip().splitlines()
    script = "\n".join([
        lines[0],
        lines[1] + " > visitor.log 2>&1 &",
        "pid=$!",
        "for i in $(seq 600); do cast components --json | python -c \"$RUNNING\" && break; sleep 0.1; done",
        "cast components --json",
        "kill $pid; wait $pid",
    ])
    running = "import json,sys; sys.exit(not any(c['id'] == 'visitor' and c['state'] == 'running' " \
              "for c in json.load(sys.stdin)))"
    out = shell(script, {**demo.cli_environment(), "RUNNING": running})
    assert out.returncode == 0, out.stderr
    rows = json.loads(out.stdout)
    visitor = next(r for r in rows if r["id"] == "visitor")
    assert visitor["subarchitecture"] == "vision" and visitor["kind"] == "managed" and visitor["state"] == "running"


def test_inspection_commands(demo: CastRun) -> None:
    lines = blocks(section("Looking at a running system: `cast ls`, `get`, `watch`, `components`, `tasks`, `stats`"),
                   "sh")[0].strip().splitlines()
    assert [line.split()[1] for line in lines] == ["components", "ls", "get", "watch", "tasks", "stats"]
    outputs = {}
    for line in lines:
        out = shell(line, demo.cli_environment())
        assert out.returncode == 0, f"{line}: {out.stderr}"
        outputs[line.split()[1]] = out.stdout
    assert "coordinator" in outputs["components"]
    assert "cast.examples.SceneObject" in outputs["ls"]
    assert "what is left of the red cube?" in outputs["get"]
    assert len(outputs["watch"].splitlines()) == 3
    assert all(json.loads(line)["subarchitecture"] == "language" for line in outputs["watch"].splitlines())
    assert re.search(r"vision\s*│\s*fifo", outputs["tasks"])
    # The metrics: the coordinator (coordination) writes questions into language's WM.
    assert "traffic" in outputs["stats"] and re.search(r"coordinator\s*│\s*coordination", outputs["stats"])
