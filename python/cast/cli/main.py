"""The ``cast`` command line: run and serve a system, the agent, and the tools (inspect, record, view, sweep)."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from cast.errors import CastError
from cast.signals import dump_stacks_on_sigquit
from cast.version import version_line

__all__ = ["build_parser", "main"]


# Each command's module (cast.cli.<module>) and the commands it adds, in the order `cast --help` lists
# them. Only the module of the command being run is imported: `cast serve`, which the orchestrator and
# every test start, then loads no recorder, Foxglove view, exporter or terminal tables (a sixth of its
# start-up CPU). `cast --help` and a command this table does not know import them all.
COMMANDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("run", ("check", "run")),
    ("serve", ("serve",)),
    ("token", ("token",)),
    ("inspection", ("ls", "get", "watch", "components", "tasks", "stats")),
    ("agent", ("agent",)),
    ("record", ("record",)),
    ("replay", ("replay", "info")),
    ("foxglove", ("foxglove",)),
    ("sweep", ("sweep",)),
    ("export", ("export",)),
    ("web", ("web",)),
    ("ros_types", ("ros-types",)),
)


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The argument parser of ``cast``: every command, or only the one ``argv`` (the arguments) names."""
    parser = argparse.ArgumentParser(prog="cast", description="CAST on gRPC: working memories for robot components")
    parser.add_argument("--version", action="version", version=version_line(),
                        help="print the library's release and the wire API it speaks, and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    named = argv[0] if argv else None
    modules = [m for m, commands in COMMANDS if named in commands] or [m for m, _ in COMMANDS]
    for module_name in modules:
        importlib.import_module(f"cast.cli.{module_name}").add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``cast`` command; the exit status."""
    arguments = sys.argv[1:] if argv is None else argv
    args = build_parser(arguments).parse_args(arguments)
    dump_stacks_on_sigquit()  # a hung `cast` command says where it is with kill -QUIT
    level = getattr(args, "log_level", "WARNING")
    logging.basicConfig(level=level, format="%(asctime)s %(name)s: %(message)s")
    try:
        return int(args.fn(args))
    except CastError as exc:
        print(f"cast {args.command}: {exc.message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0
    except OSError as exc:
        print(f"cast {args.command}: {exc}", file=sys.stderr)
        return 2
