"""One web view: the live model of a system, the door (login link, tokens) and the web server, as one.

``cast web`` and ``cast run --web`` both make a :class:`WebServer` first (so
that a taken port is said before anything else happens), then a
:class:`WebView` on it once the system answers.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from cast.client.credentials import ClientTls, TokenSource
from cast.errors import CastError
from cast.web.access import Access
from cast.web.app import make_app
from cast.web.model import LiveModel
from cast.web.server import WebServer
from cast.web.source import SystemSource

__all__ = ["WEB_ID", "WebView"]

WEB_ID = "cast-web"
"""The identity the view reads under (a reader: it writes nothing)."""


class WebView:
    """The page of the system at ``endpoint`` served on ``server``; the named CastError if the system does not answer.

    ``notice`` (callable from any thread) is told what a person should know
    later on: the next login link once one is spent, a system that stopped
    answering.
    """

    def __init__(self, server: WebServer, endpoint: str, tokens: TokenSource, tls: ClientTls | None,
                 notice: Callable[[str], None]) -> None:
        self.server = server
        self._closing = threading.Event()
        source = SystemSource(endpoint, tokens, tls)
        self.model = LiveModel(source, notice=notice)
        self.access = Access(source.accepts, lambda link: notice(
            f"a login link was used; the next one, for another browser: {link}"))
        self.access.base_url = server.url
        try:
            self.model.start()
        except CastError:
            self.model.close()
            raise
        server.serve(make_app(self.model, self.access, self._closing))

    @property
    def system_name(self) -> str:
        """The name of the system shown."""
        return self.model.source.name

    @property
    def subarchitectures(self) -> list[str]:
        """The SAs shown."""
        return self.model.source.subarchitectures

    def stop_watching(self) -> None:
        """Stop asking the servers (the page stays up, showing the last state, until :meth:`close`)."""
        self.model.close()

    def close(self) -> None:
        """End the live streams, stop serving, stop watching."""
        self._closing.set()
        self.server.close()
        self.model.close()
