"""Running C++ components from pytest: the built executables and a line protocol to drive them.

The executables live in ``build/cpp/bin`` (``make cpp``; ``$CAST_CPP_BIN_DIR``
overrides, as for the orchestrator). ``cast_probe``
(cpp_client/tests/components/cast_probe.cc) reads one command per stdin line
and answers each with one JSON line on stdout, in order. A missing build fails
the tests, it never skips them.
"""

from __future__ import annotations

import json
import os
import queue
from pathlib import Path
from typing import Any

import pytest

from cast.testing import RunningSystem, run_system
from tests.interop.child import ChildProcess

ROOT = Path(__file__).resolve().parents[2]


def cpp_bin_dir() -> Path:
    """Where the C++ component executables are."""
    return Path(os.environ.get("CAST_CPP_BIN_DIR") or ROOT / "build" / "cpp" / "bin")


def cpp_executable(name: str) -> Path:
    """The path of a built C++ executable; fails the test (never skips) when it is missing."""
    path = cpp_bin_dir() / name
    if not (path.is_file() and os.access(path, os.X_OK)):
        pytest.fail(f"the C++ component '{name}' is not built ({path} missing): run `make cpp` first")
    return path


class CppProcess(ChildProcess):
    """A C++ component process started with the launch contract; its output is collected as it comes."""

    def __init__(self, name: str, env: dict[str, str], stdin: bool = False) -> None:
        self.lines: queue.Queue[str | None] = queue.Queue()
        super().__init__(name, [str(cpp_executable(name))], env, stdin)

    def on_line(self, line: str) -> None:
        """Queue the line for :meth:`next_json`."""
        self.lines.put(line)

    def on_end(self) -> None:
        """Tell :meth:`next_json` that nothing more comes."""
        self.lines.put(None)

    def next_json(self, timeout: float = 30.0) -> dict[str, Any]:
        """The next JSON line on stdout."""
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"{self.name}: no output within {timeout} s\n{self.output()}") from None
        if line is None:
            self.proc.wait(10)
            raise AssertionError(f"{self.name} exited ({self.proc.returncode}) before answering\n{self.output()}")
        try:
            msg: dict[str, Any] = json.loads(line)
        except json.JSONDecodeError:
            raise AssertionError(f"{self.name}: not a JSON line: {line!r}\n{self.output()}") from None
        return msg


class CppProbe(CppProcess):
    """A ``cast_probe`` process: one command per line, one JSON answer per command."""

    def __init__(self, env: dict[str, str]) -> None:
        super().__init__("cast_probe", env, stdin=True)

    def ready(self, timeout: float = 30.0) -> dict[str, Any]:
        """Wait until the probe is connected and started."""
        msg = self.next_json(timeout)
        assert msg.get("ready"), f"expected the ready line, got {msg}\n{self.output()}"
        return msg

    def send(self, *words: Any) -> None:
        """Send one command line without waiting for the answer."""
        assert self.proc.stdin is not None
        line = " ".join(json.dumps(w, ensure_ascii=False) if isinstance(w, dict | list) else str(w) for w in words)
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def call(self, *words: Any, timeout: float = 30.0) -> dict[str, Any]:
        """Send a command and return its answer (ok or not)."""
        self.send(*words)
        return self.next_json(timeout)

    def ok(self, *words: Any, timeout: float = 30.0) -> dict[str, Any]:
        """Send a command that must succeed; return its result."""
        r = self.call(*words, timeout=timeout)
        assert r["ok"], f"{' '.join(map(str, words))} failed: {r}\n{self.output()}"
        result: dict[str, Any] = r["result"]
        return result

    def fails(self, error: str, *words: Any, timeout: float = 30.0) -> dict[str, Any]:
        """Send a command that must fail with the named error; return the answer."""
        r = self.call(*words, timeout=timeout)
        assert not r["ok"] and r["error"] == error, f"{' '.join(map(str, words))}: expected {error}, got {r}"
        return r

    def quit(self, timeout: float = 30.0) -> int:
        """Ask the probe to stop; return its exit status."""
        if self.proc.poll() is None:
            self.send("quit")
        return self.wait(timeout)


def cast_run(config: Path, runtime_dir: Path, extra: list[str] | None = None) -> RunningSystem:
    """``cast run CONFIG --no-status`` (the kit's run_system) with the C++ components of build/cpp/bin."""
    env = {"CAST_CPP_BIN_DIR": os.environ["CAST_CPP_BIN_DIR"]} if "CAST_CPP_BIN_DIR" in os.environ else None
    return run_system(config, *(extra or []), env=env, directory=runtime_dir.parent, runtime_dir=runtime_dir)
