"""Dynamic join: `cast token` prints the environment a hand-started component needs to join a running system."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.orchestrator.conftest import CAST, CastRun, start_cast_run, wait_for, write_config


@pytest.fixture
def system(tmp_path: Path) -> Iterator[tuple[CastRun, Path]]:
    cfg = write_config(tmp_path / "join.yaml", {
        "system": "joinable",
        "subarchitectures": {"work": {"components": {
            "producer": {"class": "orch_components:Producer", "args": {"count": 1}},
            "helper": {"class": "orch_components:Joiner", "manual": True, "args": {"note": "by hand"}},
        }}},
    })
    run = start_cast_run(tmp_path, cfg)
    yield run, cfg
    assert run.stop() == 0, run.output()


def start_by_hand(run: CastRun, env_json: str, spec: str) -> subprocess.Popen[str]:
    values = json.loads(env_json)
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("CAST_")}, **values}
    if "PYTHONPATH" not in values:
        env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1] / "orchestrator" / "components")
    return subprocess.Popen([sys.executable, "-m", "cast.run", spec], env=env, cwd=run.cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def component(run: CastRun, cid: str) -> dict[str, Any] | None:
    return next((c for c in run.cli_json("components") if c["id"] == cid), None)


def test_configured_manual_component_joins_with_cast_token_config(system: tuple[CastRun, Path]) -> None:
    run, cfg = system
    assert component(run, "helper")["state"] == "expected"  # type: ignore[index]
    out = run.cli("token", "helper", "--config", str(cfg), "--json")
    values = json.loads(out.stdout)
    assert values["CAST_SUBARCHITECTURE"] == "work" and values["CAST_COMPONENT_ID"] == "helper"
    assert values["CAST_ENDPOINT"] == run.state()["endpoint"]
    assert json.loads(values["CAST_ARGS"]) == {"note": "by hand"}
    proc = start_by_hand(run, out.stdout, "orch_components:Joiner")
    try:
        wait_for(lambda: (component(run, "helper") or {}).get("state") == "running", what="helper to join")
        wait_for(lambda: any(e["id"] == "joined-helper" for e in run.cli_json("ls", "work")), what="its entry")
    finally:
        proc.terminate()
        assert proc.wait(30) == 0
    wait_for(lambda: (component(run, "helper") or {}).get("state") == "disconnected", what="helper to leave")


def test_unconfigured_component_joins_with_an_sa(system: tuple[CastRun, Path]) -> None:
    run, _ = system
    out = run.cli("token", "stranger", "--sa", "work", "--json")
    proc = start_by_hand(run, out.stdout, "orch_components:Joiner")
    try:
        wait_for(lambda: (component(run, "stranger") or {}).get("state") == "running", what="stranger to join")
        assert any(e["id"] == "joined-stranger" and e["author"] == "stranger" for e in run.cli_json("ls", "work"))
    finally:
        proc.terminate()
        proc.wait(30)


def test_token_asks_the_running_system_for_a_known_component(system: tuple[CastRun, Path]) -> None:
    run, _ = system
    exports = run.cli("token", "helper").stdout.splitlines()
    assert "export CAST_SUBARCHITECTURE=work" in exports
    assert any(line.startswith("export CAST_TOKEN=") for line in exports)
    out = run.cli("token", "nobody", check=False)
    assert out.returncode == 2 and "is not known to the running system" in out.stderr


def test_token_needs_a_secret(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    out = subprocess.run([CAST, "token", "x", "--sa", "work", "--endpoint", "127.0.0.1:1"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "no token secret" in out.stderr
