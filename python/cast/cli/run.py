"""``cast check CONFIG`` and ``cast run CONFIG``."""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from rich.console import Console

from cast.cli.options import parse_sets
from cast.config import SystemConfig, read_config
from cast.config.engines import ENGINES, read_for_engine
from cast.config.problems import Problems
from cast.foxglove.address import DEFAULT_LISTEN
from cast.orchestrator.preflight import preflight
from cast.web.address import DEFAULT_LISTEN as WEB_LISTEN

__all__ = ["add_commands"]


def _validated(args: argparse.Namespace, builds_required: bool) -> tuple[SystemConfig | None, Problems]:
    if getattr(args, "to", None):  # cast check --to ENGINE: also what the engine cannot express (docs/deploy.md)
        config, problems = read_for_engine(args.config, args.to, Path.cwd(), parse_sets(args.set))
    else:
        config, problems = read_config(args.config, parse_sets(args.set))
    if config is not None and not problems.errors:
        preflight(config, problems, builds_required=builds_required)
        if getattr(args, "probe", False):
            _probe(config, problems)
    for problem in sorted(problems.items, key=lambda p: (p.warning, p.position.file, p.position.line)):
        print(problem, file=sys.stderr)
    return (None if problems.errors else config), problems


def _probe(config: SystemConfig, problems: Problems) -> None:
    """``--probe``: ask each host's agent whether it is up and has what its components need."""
    from cast.auth import load_secret
    from cast.config.model import ComponentConfig
    from cast.config.problems import Position
    from cast.orchestrator.remote import probe_hosts

    for placed, _host, problem in probe_hosts(config, load_secret()):
        if isinstance(placed, ComponentConfig):
            problems.error(placed.at("host"), f"components.{placed.id}.host", problem)
        elif placed is not None:
            problems.error(Position(config.source), f"servers.{placed.name}.host", problem)
        else:
            problems.error(Position(config.source), "hosts", problem)


def _describe(config: SystemConfig) -> str:
    langs = Counter(c.language for c in config.components)
    servers = ", ".join(f"{s.name} ({', '.join(s.subarchitectures)})" for s in config.servers)
    comps = ", ".join(f"{n} {lang}" for lang, n in langs.items()) or "none"
    sas, n = len(config.subarchitectures), len(config.components)
    placed = Counter(c.host for c in config.components)
    hosts = ""
    if config.hosts:
        hosts = "; hosts: " + ", ".join(f"{h} ({_count(placed[h], 'component')})" for h in ["local", *config.hosts])
    return (f"system '{config.name}': {_count(sas, 'subarchitecture')}, {_count(n, 'component')} ({comps}); "
            f"servers: {servers}{hosts}")


def _count(n: int, noun: str) -> str:
    """``n`` and ``noun``, in the plural unless there is one."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _check(args: argparse.Namespace) -> int:
    config, problems = _validated(args, builds_required=False)
    if config is None:
        errors = len(problems.errors)
        print(f"{args.config}: {errors} error{'s' if errors != 1 else ''}", file=sys.stderr)
        return 1
    print(f"{args.config}: ok: {_describe(config)}")
    return 0


def _run(args: argparse.Namespace) -> int:
    from cast.orchestrator.orchestrator import Orchestrator, RunOptions
    from cast.orchestrator.output import Output
    from cast.runtime_dir import default_runtime_dir

    config, _ = _validated(args, builds_required=True)
    if config is None:
        print(f"cast run: {args.config} has errors; nothing was started", file=sys.stderr)
        return 2
    options = RunOptions(
        run_for=args.for_seconds,
        runtime_dir=Path(args.runtime_dir) if args.runtime_dir else default_runtime_dir(),
        summary_json=Path(args.summary_json) if args.summary_json else None,
        metrics=args.metrics,
        foxglove=args.foxglove,
        record=Path(args.record) if args.record else None,
        web=args.web,
    )
    if args.exit_with_stdin:
        from cast.signals import terminate_when_stdin_closes

        terminate_when_stdin_closes()
    console = Console(highlight=False, soft_wrap=True)
    if not console.is_terminal:
        console = Console(highlight=False, soft_wrap=True, width=120)  # logs and pipes: room for the tables
    output = Output(console, live_status=not args.no_status,
                    quiet_components=args.quiet)
    result = asyncio.run(Orchestrator(config, options, output, dict(os.environ)).run())
    return result.exit_code


def add_commands(sub: Any) -> None:
    """Add ``cast check`` and ``cast run``."""
    check = sub.add_parser("check", help="validate a configuration without starting anything (exit 0 ok, 1 not)")
    check.add_argument("config", help="system configuration (YAML)")
    check.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a config variable")
    check.add_argument("--probe", action="store_true",
                       help="also ask each host's cast agent whether it is up and could launch its components "
                            "(signs with $CAST_SECRET_FILE / $CAST_SECRET, the secret the agents were given)")
    check.add_argument("--to", choices=ENGINES, help="also refuse what this engine cannot run, as `cast export --to "
                                                     "ENGINE` would (docs/deploy.md); run from the checkout's root")
    check.set_defaults(fn=_check)

    run = sub.add_parser("run", help="start a system: servers, every component, live status; Ctrl-C stops it")
    run.add_argument("config", help="system configuration (YAML)")
    run.add_argument("--for", dest="for_seconds", type=float, default=None, metavar="SECONDS",
                     help="stop after this many seconds (counted once every component is connected); exit 1 if "
                          "a component failed")
    run.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a config variable")
    run.add_argument("--no-status", action="store_true", help="no live status view (component output only)")
    run.add_argument("--quiet", action="store_true", help="do not echo component output (it is still logged)")
    run.add_argument("--runtime-dir", help="where the secret, system.json and logs go (default: $CAST_RUNTIME_DIR "
                                           "or .cast)")
    run.add_argument("--summary-json", metavar="FILE", help="also write the final summary as JSON (with the "
                                                           "servers' metrics under 'metrics': docs/experiments.md)")
    run.add_argument("--metrics", metavar="HOST:PORT",
                     help="serve the servers' metrics in Prometheus's text format on http://HOST:PORT/metrics (port "
                          "0 picks a free one; the address is printed); docs/experiments.md")
    run.add_argument("--foxglove", nargs="?", const=DEFAULT_LISTEN, metavar="HOST:PORT",
                     help=f"also serve the working memories live to the Foxglove app (default address "
                          f"{DEFAULT_LISTEN}, loopback only; port 0 picks a free one); docs/foxglove.md")
    run.add_argument("--record", metavar="FILE", help="record every change of the run, from the first, to this "
                                                       "MCAP file (never overwritten); docs/recording.md")
    run.add_argument("--web", nargs="?", const=WEB_LISTEN, metavar="HOST:PORT",
                     help=f"also serve the live web view (default address {WEB_LISTEN}, loopback only; port 0 picks "
                          "a free one; the login link is printed); docs/web.md")
    run.add_argument("--exit-with-stdin", action="store_true",
                     help="stop, as on SIGTERM, when standard input ends: started with a pipe, the system stops "
                          "when the process that started it ends, however it ends (the test kits use it)")
    run.set_defaults(fn=_run)
