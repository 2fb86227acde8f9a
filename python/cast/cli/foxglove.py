"""``cast foxglove``: a running system's working memories, live in the Foxglove app (docs/foxglove.md).

The system and the identity are found as ``cast record`` finds them
(``--endpoint``, ``$CAST_ENDPOINT``, the running ``cast run``'s runtime
directory; a read-only ``cast-foxglove`` token made from the system's secret,
unless ``$CAST_TOKEN`` or ``$CAST_TOKEN_FILE`` gives one). The first line
printed says where the view listens and whether only this machine can connect.
"""

from __future__ import annotations

import argparse
import sys
import threading
from collections.abc import Callable
from typing import Any

from cast.cli.record import Reach, add_connection_options, reach, stop_on_signals, unreachable
from cast.errors import CastError
from cast.foxglove.address import DEFAULT_LISTEN, listening_line, parse_foxglove_listen
from cast.foxglove.sink import FoxgloveSink
from cast.foxglove.view import VIEW_ID, LiveView, ViewOptions
from cast.signals import say

__all__ = ["add_commands"]


def _say(text: str) -> None:
    say(f"cast foxglove: {text}")


def _attach(sink: FoxgloveSink, where: Reach, args: argparse.Namespace, note: Callable[[str], None]) -> LiveView:
    """The view of the system, its watches created; the error the inspection commands give if it does not answer."""
    options = ViewOptions(tuple(args.subarchitecture or ()), tuple(args.type or ()))
    try:
        view = LiveView(sink, where.endpoint, where.tokens, options, where.tls, note)
    except CastError as exc:
        raise unreachable(where, exc) from None
    try:
        view.start()
    except CastError as exc:
        view.close()
        raise unreachable(where, exc) from None
    return view


def _foxglove(args: argparse.Namespace) -> int:
    address = parse_foxglove_listen(args.listen, "--listen")
    where = reach(args, VIEW_ID, privileged=False)
    held: list[str] | None = []  # notes held until the first line is out (None: printed as they come)

    def note(text: str) -> None:
        if held is None:
            say(f"cast foxglove: {text}", sys.stderr)
        else:
            held.append(text)

    stop = threading.Event()
    why: list[str] = []
    # Before the first line: whoever reads it may signal at once, and must get a clean stop.
    with stop_on_signals(stop, why):
        sink = FoxgloveSink(address, "cast", note, "--listen")  # first: a taken port is the first thing said
        try:
            view = _attach(sink, where, args, note)
            _say(listening_line(address, sink.url))
            _say(f"showing {', '.join(view.subarchitectures)} of system '{view.system_name}' from "
                 f"{where.endpoint} (Ctrl-C to stop)")
            notes, held = held or [], None
            for text in notes:
                note(text)
            view.run(stop)  # returns on a signal, or when the view cannot go on (its reason said below)
            view.close()
        finally:
            sink.close()
    _say(f"stopped by {why[0] if why else view.stop_reason or 'request'}: {sink.messages} messages sent on "
         f"{len(sink.topics)} channels")
    return 0 if why else 1


def add_commands(sub: Any) -> None:
    """Add ``cast foxglove``."""
    fox = sub.add_parser("foxglove", help="serve the working memories live to the Foxglove app (WebSocket)")
    fox.add_argument("--listen", default=DEFAULT_LISTEN, metavar="HOST:PORT",
                     help=f"where Foxglove connects (default: {DEFAULT_LISTEN}, loopback only; port 0 picks a "
                          "free one and prints it)")
    fox.add_argument("--sa", dest="subarchitecture", action="append", help="SA to show (repeatable; default: all)")
    fox.add_argument("--type", action="append", help="only entries of this full message name (repeatable)")
    add_connection_options(fox)
    fox.set_defaults(fn=_foxglove)
