"""Running a sweep: a fresh ``cast run`` per variant and repeat, results kept as they come.

Each run is ``cast run CONFIG --set ... --for SECONDS --no-status --summary-json
FILE`` in its own runtime directory, so runs share nothing but the machine. The
summary (the same JSON as ``cast run --summary-json``, with its ``metrics``) is
read back; a run that fails, or writes no summary, is recorded with its exit
code, what failed and where its output is, and the sweep goes on. ``results.json`` is
rewritten after every run, so an interrupted sweep keeps the runs that
finished.
"""

from __future__ import annotations

import json
import os
import platform
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from cast.experiments.plan import Variant, write_overlay

__all__ = ["RunRecord", "Sweep", "machine_facts"]


@dataclass
class RunRecord:
    """One run: its variant, repeat, how it ended and its summary."""

    variant: Variant
    repeat: int
    exit_code: int
    seconds: float
    summary: dict[str, Any] | None = None
    error: str = ""

    @property
    def ok(self) -> bool:
        """Ran to its end with a summary and no failure."""
        return self.exit_code == 0 and self.summary is not None

    def to_json(self) -> dict[str, Any]:
        """As stored in results.json."""
        return {"variant": self.variant.name, "repeat": self.repeat, "exit_code": self.exit_code,
                "seconds": round(self.seconds, 3), "ok": self.ok, "error": self.error, "summary": self.summary}


@cache
def machine_facts() -> dict[str, Any]:
    """What the numbers depend on: the machine, the interpreter and the code's version."""
    facts: dict[str, Any] = {
        "platform": platform.platform(), "machine": platform.machine(), "processor": platform.processor(),
        "cpus": os.cpu_count(), "python": platform.python_version(),
    }
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            facts["memory_kib"] = int(meminfo.readline().split()[1])
    except (OSError, ValueError, IndexError):
        pass
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5)
        if commit.returncode == 0:
            facts["git_commit"] = commit.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return facts


@dataclass
class Sweep:
    """A sweep's settings and the runs made so far."""

    config: Path
    out: Path
    variants: list[Variant]
    seconds: float
    repeat: int
    seed: int = 0
    sets: dict[str, str] = field(default_factory=dict)  # fixed --set values, applied to every run
    runs: list[RunRecord] = field(default_factory=list)
    interrupted: bool = False
    _child: subprocess.Popen[str] | None = None

    @property
    def total(self) -> int:
        """How many runs the sweep makes."""
        return len(self.variants) * self.repeat

    def plan(self) -> list[tuple[Variant, int]]:
        """Every (variant, repeat), repeats of one variant apart: a slow spell of the machine spreads out."""
        return [(v, k) for k in range(1, self.repeat + 1) for v in self.variants]

    def command(self, variant: Variant, repeat: int) -> tuple[list[str], Path]:
        """The ``cast run`` command of one run and its summary file."""
        run_dir = self.out / "runs" / f"{variant.slug}-r{repeat}"
        run_dir.mkdir(parents=True, exist_ok=True)
        config = write_overlay(self.config, variant, self.out / "configs")
        summary = run_dir / "summary.json"
        summary.unlink(missing_ok=True)
        argv = [sys.executable, "-m", "cast.cli", "run", str(config), "--for", f"{self.seconds:g}", "--no-status",
                "--summary-json", str(summary), "--runtime-dir", str(run_dir / "rt")]
        # The same seed for every run: a configuration that draws random numbers reads ${SEED}.
        for name, value in {"SEED": str(self.seed), **self.sets, **dict(variant.sets)}.items():
            argv += ["--set", f"{name}={value}"]
        return argv, summary

    def run_one(self, variant: Variant, repeat: int) -> RunRecord:
        """Run one variant once; its record (never raises for a failed run)."""
        argv, summary_path = self.command(variant, repeat)
        log_path = summary_path.parent / "output.log"
        started = time.monotonic()
        with log_path.open("w", encoding="utf-8") as log:
            env = dict(os.environ, PYTHONHASHSEED=str(self.seed))
            # Started in a new session: Ctrl-C reaches the sweep only, which stops the run cleanly.
            self._child = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, text=True, env=env,
                                           start_new_session=True)
            try:
                code = self._child.wait()
            finally:
                self._child = None
        seconds = time.monotonic() - started
        summary: dict[str, Any] | None = None
        error = ""
        try:
            summary = json.loads(summary_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            error = f"no summary ({exc.__class__.__name__})"
        if summary is not None and summary.get("failures"):
            error = "; ".join(str(f) for f in summary["failures"])
        if code != 0 and not error:
            error = f"cast run exited {code}"
        if error:
            error += f" (its output: {log_path})"
        return RunRecord(variant, repeat, code, seconds, summary, error)

    def stop(self) -> None:
        """Interrupt: the current run is stopped as Ctrl-C stops ``cast run``; no further run starts."""
        self.interrupted = True
        child = self._child
        if child is not None and child.poll() is None:
            child.send_signal(signal.SIGINT)

    def run(self, progress: Callable[[RunRecord], None] | None = None) -> list[RunRecord]:
        """Every planned run that has not been made, saving results.json after each."""
        self.out.mkdir(parents=True, exist_ok=True)
        for variant, repeat in self.plan():
            if self.interrupted:
                break
            record = self.run_one(variant, repeat)
            if self.interrupted and record.exit_code != 0:
                break  # the run cut short is not a result
            self.runs.append(record)
            self.save()
            if progress is not None:
                progress(record)
        self.save()
        return self.runs

    def save(self) -> None:
        """Write results.json: the sweep's settings, the machine, every run so far."""
        data = {
            "config": str(self.config), "seconds": self.seconds, "repeat": self.repeat, "seed": self.seed,
            "sets": self.sets, "variants": [v.to_json() for v in self.variants],
            "planned_runs": self.total, "interrupted": self.interrupted, "machine": machine_facts(),
            "runs": [r.to_json() for r in self.runs],
        }
        tmp = self.out / "results.json.tmp"
        tmp.write_text(json.dumps(data, indent=2) + "\n")
        tmp.replace(self.out / "results.json")
