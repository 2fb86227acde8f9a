"""``cast sweep CONFIG --vary NAME=a,b --policy SA=fifo,priority --for S --repeat K -o DIR``: compare designs."""

from __future__ import annotations

import argparse
import shlex
import signal
import sys
import tempfile
import time
from pathlib import Path
from types import FrameType
from typing import Any

from cast.cli.options import parse_sets
from cast.errors import InvalidArgumentError

__all__ = ["add_commands"]


def _sweep(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from cast.config import read_config
    from cast.experiments.plan import parse_axes, variants
    from cast.experiments.report import render_report, summarise
    from cast.experiments.sweep import RunRecord, Sweep

    config = Path(args.config)
    if args.seconds <= 0:
        raise InvalidArgumentError(f"--for {args.seconds:g}: give the length of each run in seconds (> 0)")
    if args.repeat < 1:
        raise InvalidArgumentError(f"--repeat {args.repeat}: give at least 1")
    vary, policy = parse_axes(args.vary, "--vary"), parse_axes(args.policy, "--policy")
    planned = variants(vary, policy)
    fixed = parse_sets(args.set)
    _check_first(config, planned, fixed, read_config)
    sweep = Sweep(config, Path(args.out), planned, args.seconds, args.repeat, args.seed, fixed)
    console = Console(stderr=True)
    console.print(f"cast sweep: {len(planned)} variant(s) x {args.repeat} repeat(s) = {sweep.total} runs of "
                  f"{args.seconds:g} s each, into {sweep.out}")

    def interrupted(signum: int, frame: FrameType | None) -> None:
        console.print("cast sweep: stopping after the current run is stopped; the finished runs are kept")
        sweep.stop()

    old = signal.signal(signal.SIGINT, interrupted)
    old_term = signal.signal(signal.SIGTERM, interrupted)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("left"),
               TimeRemainingColumn())
    try:
        with Progress(*columns, console=console, transient=False) as progress:
            task = progress.add_task("runs", total=sweep.total)

            def done(record: RunRecord) -> None:
                state = "ok" if record.ok else f"FAILED ({record.error[:120]})"
                progress.console.print(f"  {record.variant.name} #{record.repeat}: {state} in {record.seconds:.1f} s")
                progress.advance(task)

            started = time.monotonic()
            sweep.run(done)
    finally:
        signal.signal(signal.SIGINT, old)
        signal.signal(signal.SIGTERM, old_term)
    results = summarise(sweep)
    plots: list[str] = []
    if not args.no_plots and any(r.ok for r in sweep.runs):
        from cast.experiments.plots import write_plots
        plots = write_plots(results, sweep.out)
    command = "cast sweep " + shlex.join(sys.argv[2:] if sys.argv[1:2] == ["sweep"] else sys.argv[1:])
    (sweep.out / "report.md").write_text(render_report(sweep, results, command, plots))
    failed = sum(1 for r in sweep.runs if not r.ok)
    print(f"{len(sweep.runs)} of {sweep.total} runs in {time.monotonic() - started:.0f} s, {failed} failed; "
          f"wrote {sweep.out / 'results.json'}, {sweep.out / 'report.md'}"
          + (f" and {len(plots)} plot(s)" if plots else ""))
    if sweep.interrupted:
        return 130
    return 1 if failed else 0


def _check_first(config: Path, planned: list[Any], fixed: dict[str, str], read_config: Any) -> None:
    """Every variant's configuration is valid before the first run starts (a typo costs no sweep)."""
    from cast.experiments.plan import write_overlay

    with tempfile.TemporaryDirectory(prefix="cast-sweep-check-") as scratch:
        for variant in planned:
            path = write_overlay(config, variant, Path(scratch))
            overrides = {**fixed, "SEED": "0", **dict(variant.sets)}
            found, problems = read_config(path, overrides)
            if found is None or problems.errors:
                first = problems.errors[0] if problems.errors else "it cannot be read"
                raise InvalidArgumentError(f"variant {variant.name}: the configuration has errors, so no run "
                                           f"started: {first} (cast check {config} with the same --set shows all)")
            if not variant.policies:
                continue
            # The overlay would add an SA it names, so the SAs are the user's file's own.
            plain, _ = read_config(config, overrides)
            known = set(plain.subarchitectures) if plain is not None else set()
            for sa, _policy in variant.policies:
                if sa not in known:
                    raise InvalidArgumentError(f"--policy {sa}=...: variant {variant.name} has no SA '{sa}' (its SAs: "
                                               f"{', '.join(sorted(known))}); name an SA of the configuration, or "
                                               "vary a variable the file uses in its task_manager: instead")


def add_commands(sub: Any) -> None:
    """Add ``cast sweep``."""
    sweep = sub.add_parser("sweep", help="run a configuration under every combination of variables and policies, "
                                         "and compare the runs (docs/experiments.md)")
    sweep.add_argument("config", help="system configuration (YAML)")
    sweep.add_argument("--vary", action="append", default=[], metavar="NAME=a,b,...",
                       help="a configuration variable and its values (repeatable: every combination runs)")
    sweep.add_argument("--policy", action="append", default=[], metavar="SA=p1,p2,...",
                       help="an SA's task-manager policies to compare (repeatable)")
    sweep.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                       help="a variable fixed for every run")
    sweep.add_argument("--for", dest="seconds", type=float, required=True, metavar="SECONDS",
                       help="how long each run lasts after all its components started")
    sweep.add_argument("--repeat", type=int, default=1, help="runs per variant (the report shows their spread)")
    sweep.add_argument("--seed", type=int, default=0, help="the SEED variable and PYTHONHASHSEED of every run")
    sweep.add_argument("-o", "--out", required=True, metavar="DIR", help="where results.json, report.md and "
                                                                       "the plots go")
    sweep.add_argument("--no-plots", action="store_true", help="no PNG plots (no matplotlib needed)")
    sweep.set_defaults(fn=_sweep)
