"""Fixtures of the orchestrator tests: configurations, an orchestrator embedded in the test, `cast run` processes."""

from __future__ import annotations

import asyncio
import io
import os
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml
from rich.console import Console

from cast.config import load_config
from cast.config.problems import Problems
from cast.orchestrator.orchestrator import Orchestrator, RunOptions, RunResult
from cast.orchestrator.output import Output
from cast.orchestrator.preflight import preflight
from cast.testing import RunningSystem, run_system
from tests.conftest import ROOT, wait_for

COMPONENTS = Path(__file__).resolve().parent / "components"
CAST = str(Path(sys.executable).parent / "cast")


def write_config(path: Path, data: dict[str, Any]) -> Path:
    """Write a configuration with the test components on its python_path."""
    data = {"python_path": [str(COMPONENTS)], **data}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@dataclass
class Embedded:
    """An orchestrator running on a thread of the test process, its servers' objects at hand."""

    orchestrator: Orchestrator
    output: io.StringIO
    thread: threading.Thread
    result: list[RunResult] = field(default_factory=list)

    @property
    def servers(self) -> Any:
        return self.orchestrator.servers

    def system(self, sa: str) -> Any:
        return self.orchestrator.servers.hosting(sa).system

    def stop(self) -> RunResult:
        self.orchestrator.request_stop()
        self.thread.join(60)
        assert not self.thread.is_alive(), "the orchestrator did not stop"
        return self.result[0]

    def text(self) -> str:
        return self.output.getvalue()


@pytest.fixture
def embedded(tmp_path: Path) -> Iterator[Callable[..., Embedded]]:
    """Start an orchestrator for a configuration file inside the test process; stopped at the end."""
    started: list[Embedded] = []

    def start(config_path: Path, sets: dict[str, str] | None = None, wait: bool = True) -> Embedded:
        config = load_config(config_path, sets)
        problems = Problems()
        preflight(config, problems, builds_required=True)
        problems.raise_if_errors()
        buffer = io.StringIO()
        output = Output(Console(file=buffer, width=200, highlight=False), live_status=False)
        options = RunOptions(runtime_dir=tmp_path / f"runtime{len(started)}")
        orch = Orchestrator(config, options, output, dict(os.environ))
        box: list[RunResult] = []
        errors: list[BaseException] = []

        def body() -> None:
            try:
                box.append(asyncio.run(orch.run()))
            except BaseException as exc:
                errors.append(exc)
                raise

        thread = threading.Thread(target=body, name="orchestrator", daemon=True)
        thread.start()
        handle = Embedded(orch, buffer, thread, box)
        started.append(handle)
        if wait:
            wait_for(lambda: orch.connected.is_set() or errors or not thread.is_alive(), what="components to connect")
            assert not errors, errors
            assert orch.connected.is_set(), buffer.getvalue()
        return handle

    yield start
    for handle in started:
        if handle.thread.is_alive():
            handle.stop()


CastRun = RunningSystem
"""A `cast run` process with its own runtime directory: the kit's (cast.testing.run_system)."""


def start_cast_run(
    cwd: Path, config: Path, *extra: str, env: dict[str, str] | None = None, until: str = "components started in"
) -> CastRun:
    """Start `cast run CONFIG --no-status` in ``cwd`` (runtime directory ``cwd/runtime``) and wait for the line
    ``until`` (default: every component started)."""
    return run_system(config, *extra, env=env, cwd=cwd, until=until, directory=cwd)


def build_examples() -> Path:
    """Generate the demo's entry types as `make examples` does (if missing); return the demo config."""
    out = ROOT / "build" / "python-examples"
    protos = sorted((ROOT / "examples" / "proto" / "castdemo").glob("*.proto"))
    stamp = out / ".generated"
    if not stamp.exists() or any(p.stat().st_mtime > stamp.stat().st_mtime for p in protos):
        out.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            [sys.executable, "-m", "grpc_tools.protoc", f"-I{ROOT / 'examples' / 'proto'}", f"--python_out={out}",
             *map(str, protos)],
            check=True,
        )
        stamp.touch()
    return ROOT / "configs" / "demo.yaml"


@pytest.fixture(scope="session")
def demo_built() -> Path:
    """The demo's entry types are generated; the demo config's path."""
    return build_examples()
