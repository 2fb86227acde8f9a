"""The inspection commands on a system whose SAs are served by two servers, and explicit addressing."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from cast.auth import peek
from cast.core.records import Identity
from tests.orchestrator.conftest import CAST, CastRun, start_cast_run, wait_for, write_config


@pytest.fixture
def two_servers(tmp_path: Path) -> Iterator[CastRun]:
    cfg = write_config(tmp_path / "two.yaml", {
        "system": "two",
        "subarchitectures": {
            "vision": {"task_manager": {"policy": "fifo", "max_concurrent": 1}, "components": {
                "worker": {"kind": "managed", "class": "orch_components:Worker", "args": {"source_sa": "motor"}}}},
            "motor": {"task_manager": {"policy": "exclusive"}, "components": {
                "producer": {"class": "orch_components:Producer", "args": {"count": 2}}}},
        },
        "servers": {"main": {"subarchitectures": ["vision"]}, "motion": {"subarchitectures": ["motor"]}},
    })
    run = start_cast_run(tmp_path, cfg)
    yield run
    assert run.stop() == 0, run.output()


def test_commands_reach_the_sa_on_the_other_server(two_servers: CastRun) -> None:
    run = two_servers
    servers = run.state()["servers"]
    assert servers["main"]["endpoint"] != servers["motion"]["endpoint"]
    wait_for(lambda: len(run.cli_json("ls", "vision")) >= 2, what="the worker's results")
    motor = run.cli_json("ls", "motor")
    assert {e["id"] for e in motor} == {"item-0", "item-1"}
    assert {e["subarchitecture"] for e in run.cli_json("ls")} == {"vision", "motor"}
    assert run.cli_json("get", "motor", "item-1")["value"] == "item 1 from motor"
    out = _watch_or_dump(run, "--sa", "motor", "--sa", "vision", "--from", "1", "--type",
                         "google.protobuf.StringValue", "--count", "2")
    assert [json.loads(line)["subarchitecture"] for line in out.splitlines()] == ["motor", "motor"]
    counters = {c["subarchitecture"]: c["policy"] for c in run.cli_json("tasks")["subarchitectures"]}
    assert counters == {"vision": "fifo(max_concurrent=1)", "motor": "exclusive"}


def _watch_or_dump(run: CastRun, *args: str) -> str:
    """`cast watch ARGS`'s output; if it has not ended in 60 s, fail with its threads' stacks and the system's state.

    A watch that stopped short of its count once, under the load of the whole suite, and never alone:
    what it waited on, and what the servers held, is what a rerun cannot tell.
    """
    env = {**run.cli_environment(), "PYTHONFAULTHANDLER": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "cast.cli", "watch", *args], env=env, cwd=run.cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)  # faulthandler prints every thread's stack
        out, err = proc.communicate(timeout=30)
        state = {sa: run.cli_json("ls", sa) for sa in ("motor", "vision")}
        raise AssertionError(f"cast watch {' '.join(args)} did not end in 60 s\nprinted:\n{out}\nstacks:\n{err}\n"
                             f"entries: {state}\nsystem:\n{run.output()[-4000:]}") from None
    assert proc.returncode == 0, out + err
    return out


def test_endpoint_and_secret_given_explicitly(two_servers: CastRun, tmp_path: Path) -> None:
    run = two_servers
    endpoint = run.state()["endpoint"]
    secret = run.runtime_dir / "secret"
    base = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    out = subprocess.run([CAST, "components", "--json", "--endpoint", endpoint, "--secret-file", str(secret)],
                         cwd=tmp_path, env=base, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert {c["id"] for c in json.loads(out.stdout)} == {"worker", "producer"}
    env = {**base, "CAST_ENDPOINT": endpoint, "CAST_SECRET": secret.read_text().strip()}
    out = subprocess.run([CAST, "ls", "motor", "--json"], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    out = subprocess.run([CAST, "ls", "--json"], cwd=tmp_path, env={**env, "CAST_SECRET": "x" * 32},
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "token signature does not match" in out.stderr


def test_a_secret_file_on_the_command_line_beats_cast_token_in_the_environment(tmp_path: Path) -> None:
    from cast.cli.connect import tool_token
    from cast.runtime_dir import RuntimeDir

    secret = tmp_path / "secret"
    secret.write_text("s" * 40 + "\n")
    made = tool_token(str(secret), RuntimeDir(tmp_path / "rt"), {"CAST_TOKEN": "from-the-environment"})
    assert made != "from-the-environment" and peek(made) == Identity("cast-cli", "", False)
    assert tool_token(None, RuntimeDir(tmp_path / "rt"), {"CAST_TOKEN": "from-the-environment"}) == \
        "from-the-environment"
