"""``cast replay FILE`` and ``cast info FILE``: a recording written back into a running system, or described."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path
from typing import Any

from rich.console import Console

from cast.cli.record import add_connection_options, reach, stop_on_signals, unreachable
from cast.cli.render import print_json, print_table
from cast.client.grpc_transport import GrpcTransport
from cast.core.sessions import ComponentState
from cast.errors import CastError, InvalidArgumentError, SchemaConflictError
from cast.recording.info import describe
from cast.recording.reading import Recording
from cast.recording.replay import Replayer, ReplayOptions, ReplayReport

__all__ = ["add_commands"]

REPLAY_ID = "cast-replay"


def _sa_map(items: list[str] | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items or ():
        recorded, sep, live = item.partition("=")
        if not sep or not recorded or not live:
            raise InvalidArgumentError(f"--sa-map {item!r}: write RECORDED=LIVE, e.g. --sa-map vision=vision2")
        out[recorded] = live
    return out


def _rate(text: str) -> float | None:
    if text == "max":
        return None
    try:
        return float(text)
    except ValueError:
        raise InvalidArgumentError(f"--rate {text!r}: give a speed factor (1.0: as recorded, 2: twice as fast) "
                                   "or max") from None


def _replay(args: argparse.Namespace) -> int:
    options = ReplayOptions(rate=_rate(args.rate), sa_map=_sa_map(args.sa_map), types=tuple(args.type or ()),
                            loop=args.loop, start_s=args.start, end_s=args.end)
    console = Console(stderr=True, highlight=False)
    with Recording(Path(args.file)) as recording:
        where = reach(args, REPLAY_ID, privileged=True)
        try:
            transport = GrpcTransport(where.endpoint, where.tokens, where.told, tls=where.tls)
        except CastError as exc:
            raise unreachable(where, exc) from None
        try:
            transport.start_session("python", "unmanaged", lambda: ComponentState.RUNNING)
            replayer = Replayer(recording, transport, options,
                                lambda line: console.print(f"cast replay: {line}", soft_wrap=True, markup=False))
            try:
                replayer.prepare()
            except SchemaConflictError as exc:
                raise InvalidArgumentError(
                    f"a type in {args.file} has another schema in the live system: {exc.message}; nothing was "
                    "written (replay into a system built with the recorded types, or leave that type out with "
                    "--type)") from None
            stop = threading.Event()
            why: list[str] = []
            targets = ", ".join(f"{sa}->{t}" if sa != t else sa for sa, t in replayer.targets.items())
            console.print(f"cast replay: {args.file} into {targets or 'nothing'} at "
                          f"{'full speed' if options.rate is None else f'{options.rate:g} x'}"
                          f"{', looping (Ctrl-C to stop)' if options.loop else ''}", soft_wrap=True, markup=False)
            for gap in recording.gaps():
                console.print(f"cast replay: the recording has a {gap.describe()}", soft_wrap=True, markup=False)
            with stop_on_signals(stop, why):
                report = replayer.run(stop)
        finally:
            transport.close()
    return _report(console, report, why)


def _report(console: Console, report: ReplayReport, why: list[str]) -> int:
    w = report.written
    console.print(f"cast replay: {sum(w.values())} changes written ({w['add']} add, {w['overwrite']} overwrite, "
                  f"{w['delete']} delete) in {report.passes} pass(es){'; stopped by ' + why[0] if why else ''}; "
                  f"{len(report.conflicts)} conflict(s), {len(report.errors)} error(s)", soft_wrap=True, markup=False)
    for reason, n in report.skipped.items():
        console.print(f"cast replay: not written: {n} {reason}", soft_wrap=True, markup=False)
    return 1 if report.conflicts or report.errors else 0


def _info(args: argparse.Namespace) -> int:
    with Recording(Path(args.file)) as recording:
        info = describe(recording)
    if args.json:
        print_json(info)
        return 0
    print(f"{info['file']}: system '{info['system']}' at {info['endpoint']}, {info['changes']} changes from "
          f"{info['start'] or '-'} to {info['end'] or '-'} ({info['duration_s']:.3f} s), {len(info['gaps'])} gap(s)")
    print_table("subarchitectures", ["SA", "changes", "add", "overwrite", "delete", "revisions"],
                [[r["subarchitecture"], r["changes"], r["add"], r["overwrite"], r["delete"],
                  f"{r['first_revision']}..{r['last_revision']}" if r["changes"] else ""]
                 for r in info["subarchitectures"]],
                numeric=["changes", "add", "overwrite", "delete"])
    print_table("channels", ["topic", "type", "messages", "schema"],
                [[c["topic"], c["type"], c["messages"], c["schema"]] for c in info["channels"]],
                numeric=["messages"])
    if info["gaps"]:
        print_table("gaps (changes not in the recording)", ["SA", "after revision", "resumed at", "missing", "why"],
                    [[g["subarchitecture"], g["last_revision"], g["resumed_revision"],
                      "unknown" if g["missing"] is None else g["missing"], g["reason"]] for g in info["gaps"]],
                    numeric=["after revision", "resumed at", "missing"])
    return 0


def add_commands(sub: Any) -> None:
    """Add ``cast replay`` and ``cast info``."""
    rep = sub.add_parser("replay", help="write a recording's changes into a running system, with their timing")
    rep.add_argument("file", help="a recording made by `cast record`")
    rep.add_argument("--rate", default="1.0", help="speed factor (1.0: as recorded, 2: twice as fast), or max")
    rep.add_argument("--sa-map", action="append", metavar="RECORDED=LIVE",
                     help="write a recorded SA's changes into another live SA (repeatable)")
    rep.add_argument("--type", action="append", help="only entries of this full message name (repeatable)")
    rep.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C or SIGTERM")
    rep.add_argument("--from", dest="start", type=float, default=0.0,
                     help="start this many seconds after the recording's first change")
    rep.add_argument("--to", dest="end", type=float, help="stop this many seconds after the recording's first change")
    add_connection_options(rep)
    rep.set_defaults(fn=_replay)

    info = sub.add_parser("info", help="what a recording holds: SAs, types, counts, time span, gaps")
    info.add_argument("file", help="a recording made by `cast record`")
    info.add_argument("--json", action="store_true", help="JSON for scripts instead of tables")
    info.set_defaults(fn=_info)
