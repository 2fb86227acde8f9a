"""The start barrier (cast.core.barrier): every component's start() before any component's run().

A watcher registers in start(), writers write first thing in run(): the watchers see every write,
every time. A slow start() holds everyone's run() back; a component that joins by hand, or is
restarted after a crash, runs at once. The same across C++ and Java: tests/interop/test_start_barrier.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.wrappers_pb2 import Int64Value

from tests.orchestrator.conftest import COMPONENTS, Embedded, start_cast_run, wait_for, write_config

WRITES = 20
RUNS = 5  # it failed within a few runs without the barrier


def seen(entries: list[tuple[str, int]]) -> dict[tuple[str, str], int]:
    """The watchers' reports ``seen-<watcher>-<writer>`` = k, as {(watcher, writer): k}."""
    found = {}
    for entry_id, value in entries:
        if entry_id.startswith("seen-"):
            watcher, _, writer = entry_id.removeprefix("seen-").partition("-w-")
            found[(watcher, "w-" + writer)] = value
    return found


def barrier_config(tmp_path: Path, writers: dict[str, dict[str, Any]], watchers: dict[str, dict[str, Any]]) -> Path:
    """Writers in SA ``a`` that write into ``b`` first thing in run(); watchers in ``b`` that watch from start()."""
    writer_specs = {cid: {"privileged": True, "args": {"sa": "b", "count": WRITES}, **spec}
                    for cid, spec in writers.items()}
    return write_config(tmp_path / "barrier.yaml", {
        "system": "barrier",
        "subarchitectures": {"a": {"components": writer_specs}, "b": {"components": watchers}},
    })


@pytest.mark.parametrize("attempt", range(RUNS))
def test_watchers_registered_in_start_see_every_write_made_first_thing_in_run(
    tmp_path: Path, embedded: Callable[..., Embedded], attempt: int
) -> None:
    writer = {"class": "barrier_components:BarrierWriter"}
    watcher = {"class": "barrier_components:BarrierWatcher"}
    cfg = barrier_config(
        tmp_path,
        {"w-remote": writer, "w-inproc": {**writer, "in_process": True}},
        {"watch-remote": watcher, "watch-inproc": {**watcher, "in_process": True}},
    )
    run = embedded(cfg)
    pairs = [(w, src) for w in ("watch-remote", "watch-inproc") for src in ("w-remote", "w-inproc")]

    def reports() -> dict[tuple[str, str], int]:
        return seen([(e.id, Int64Value.FromString(e.data).value) for e in run.system("b").host.all_entries("b")])

    wait_for(lambda: set(pairs) <= set(reports()), what="every watcher to see every writer's end")
    assert reports() == {pair: WRITES for pair in pairs}, run.text()
    assert "all 4 components started in" in run.text() and "run() released" in run.text()


def _gate_system(tmp_path: Path, extra: dict[str, Any] | None = None) -> tuple[Path, Path]:
    gate = tmp_path / "gate"
    cfg = write_config(tmp_path / "gate.yaml", {
        "system": "gate",
        "subarchitectures": {"work": {"components": {
            "gate": {"class": "barrier_components:BarrierGate", "args": {"gate": str(gate)}},
            "first": {"class": "barrier_components:FirstWrite"},
            **(extra or {}),
        }}},
    })
    return cfg, gate


def test_a_slow_start_holds_every_run_back_and_a_joiner_or_a_restart_runs_at_once(tmp_path: Path) -> None:
    cfg, gate = _gate_system(tmp_path, {"helper": {"class": "barrier_components:FirstWrite", "manual": True}})
    run = start_cast_run(tmp_path, cfg, until="cast: system 'gate'")
    try:
        def states() -> dict[str, str]:
            return {c["id"]: c["state"] for c in run.cli_json("components")}

        # `first` finished start() and waits at the barrier; `gate` is still in its start().
        wait_for(lambda: states().get("first") == "started", what="first to reach the barrier")
        assert states()["gate"] == "starting"
        # A component that joins by hand is not held: it runs while the barrier is still closed.
        token = run.cli("token", "helper", "--config", str(cfg), "--json").stdout
        joiner = _start_by_hand(run.cwd, token, "barrier_components:FirstWrite")
        try:
            wait_for(lambda: any(e["id"] == "ran-helper" for e in run.cli_json("ls", "work")),
                     what="the joiner's run()")
            ids = {e["id"] for e in run.cli_json("ls", "work")}
            assert "ran-first" not in ids and states()["first"] == "started", "run() began before gate started"
            gate.touch()
            wait_for(lambda: {"ran-first", "gate-ran"} <= {e["id"] for e in run.cli_json("ls", "work")},
                     what="run() of first and gate after the release")
            # Released only after gate's start() ended: its last write comes before first's run().
            entries = {e["id"]: e for e in run.cli_json("ls", "work")}
            assert entries["gate-opened"]["revision"] < entries["ran-first"]["revision"]
            assert states()["first"] == "running"
            # A component restarted after a crash runs at once: the barrier stays open.
            first = next(c for c in run.cli_json("components") if c["id"] == "first")
            os.kill(first["pid"], signal.SIGKILL)
            wait_for(lambda: any(e["id"].startswith("ran-first-") for e in run.cli_json("ls", "work")),
                     what="the restarted component's run()")
        finally:
            joiner.terminate()
            joiner.wait(30)
    finally:
        run.stop()
    assert "all 2 components started in" in run.output()


def _start_by_hand(cwd: Path, env_json: str, spec: str) -> subprocess.Popen[str]:
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("CAST_")}, **json.loads(env_json)}
    env["PYTHONPATH"] = str(COMPONENTS)
    return subprocess.Popen([sys.executable, "-m", "cast.run", spec], env=env, cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
