"""``cast web``: a running system in the browser: architecture, working memories, task managers, rates (docs/web.md).

The system and the identity are found as ``cast foxglove`` finds them
(``--endpoint``, ``$CAST_ENDPOINT``, the running ``cast run``'s runtime
directory; a read-only ``cast-web`` token made from the system's secret,
unless ``$CAST_TOKEN`` or ``$CAST_TOKEN_FILE`` gives one). The first line says
where the page listens and whether only this machine can reach it; the second
is the one-time login link.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from typing import Any

from cast.cli.record import add_connection_options, reach, stop_on_signals, unreachable
from cast.errors import CastError
from cast.signals import say
from cast.web.address import DEFAULT_LISTEN, listening_line, parse_web_listen

__all__ = ["add_commands"]


def _say(text: str) -> None:
    say(f"cast web: {text}")


def _note(text: str) -> None:
    say(f"cast web: {text}", sys.stderr)


def _web(args: argparse.Namespace) -> int:
    from cast.web.server import WebServer  # the web framework, only for this command
    from cast.web.view import WEB_ID, WebView

    # The page and this command say when the system does not answer; the client library's warning per
    # reconnection attempt of the watch stream would only repeat it every few seconds.
    logging.getLogger("cast.client").setLevel(logging.ERROR)
    address = parse_web_listen(args.listen, "--listen")
    where = reach(args, WEB_ID, privileged=False)
    stop = threading.Event()
    why: list[str] = []
    # Before the first line: whoever reads it may signal at once, and must get a clean stop.
    with stop_on_signals(stop, why):
        server = WebServer(address, "--listen")  # first: a taken port is the first thing said
        try:
            try:
                view = WebView(server, where.endpoint, where.tokens, where.tls, _say)
            except CastError as exc:
                raise unreachable(where, exc) from None
            try:
                _say(listening_line(address, server.url))
                _say(f"open {view.access.login_link()} (this login link works once; the next is printed when it "
                     "is used)")
                _say(f"showing {', '.join(view.subarchitectures)} of system '{view.system_name}' from "
                     f"{where.endpoint}, read-only (Ctrl-C to stop)")
                while not stop.wait(0.5):
                    if server.error is not None:
                        _note(f"the web server failed: {server.error}")
                        break
            finally:
                view.close()
        finally:
            server.close()
    _say(f"stopped by {why[0] if why else 'an error'}")
    return 0 if why else 1


def add_commands(sub: Any) -> None:
    """Add ``cast web``."""
    web = sub.add_parser("web", help="show the running system in a browser: architecture, working memories, task "
                                     "managers, rates (read-only; docs/web.md)")
    web.add_argument("--listen", default=DEFAULT_LISTEN, metavar="HOST:PORT",
                     help=f"where the page listens (default: {DEFAULT_LISTEN}, loopback only; port 0 picks a free "
                          "one and prints it)")
    add_connection_options(web)
    web.set_defaults(fn=_web)
