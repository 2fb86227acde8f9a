"""``cast run --web``: the web view inside the orchestrator, beside the servers it runs.

Bound before anything starts (a taken port stops ``cast run`` with exit 2,
nothing started); the steps are those of every attached tool
(:mod:`cast.attach`), and the orchestrator's event loop never waits for a
browser.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from cast.attach import AttachedTool
from cast.client.credentials import ClientTls, TokenSource
from cast.web.address import listening_line, parse_web_listen
from cast.web.server import WebServer
from cast.web.view import WEB_ID, WebView

__all__ = ["RunWeb"]


class RunWeb(AttachedTool):
    """The web view of one ``cast run``: bound at construction, then :meth:`attach`, then :meth:`close`."""

    tool_id = WEB_ID

    def __init__(self, listen: str, notice: Callable[[str], None]) -> None:
        super().__init__(notice)
        self.server = WebServer(parse_web_listen(listen, "--web"), "--web")
        self._view: WebView | None = None
        self._lock = threading.Lock()

    @property
    def port(self) -> int:
        """The bound port."""
        return self.server.port

    def _start(self, endpoint: str, tokens: TokenSource, tls: ClientTls | None) -> None:
        view = WebView(self.server, endpoint, tokens, tls, self._notice)
        with self._lock:
            self._view = view
        self._notice(listening_line(self.server.address, self.server.url))
        self._notice(f"open {view.access.login_link()} (the login link works once; the next is printed when used)")

    def _not_started(self, why: str) -> str:
        return f"{listening_line(self.server.address, self.server.url)}, but it shows nothing: {why}"

    def stop_watching(self) -> None:
        """The components have stopped: stop asking the servers (the page stays up until :meth:`close`)."""
        with self._lock:
            view = self._view
        if view is not None:
            view.stop_watching()

    def close(self) -> None:
        """Stop serving and release the port (also when never attached)."""
        with self._lock:
            view, self._view = self._view, None
        if view is not None:
            view.close()
        else:
            self.server.close()
