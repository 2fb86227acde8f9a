"""The ``cast`` command line: run and serve a system, the agent, and the tools (inspect, record, view, sweep)."""

from __future__ import annotations

import argparse
import logging
import sys

from cast.cli import agent, export, foxglove, inspection, record, replay, ros_types, run, serve, sweep, token, web
from cast.errors import CastError
from cast.signals import dump_stacks_on_sigquit
from cast.version import version_line

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``cast``."""
    parser = argparse.ArgumentParser(prog="cast", description="CAST on gRPC: working memories for robot components")
    parser.add_argument("--version", action="version", version=version_line(),
                        help="print the library's release and the wire API it speaks, and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run.add_commands(sub)
    serve.add_command(sub)
    token.add_command(sub)
    inspection.add_commands(sub)
    agent.add_command(sub)
    record.add_command(sub)
    replay.add_commands(sub)
    foxglove.add_command(sub)
    sweep.add_command(sub)
    export.add_command(sub)
    web.add_command(sub)
    ros_types.add_command(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``cast`` command; the exit status."""
    args = build_parser().parse_args(argv)
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
