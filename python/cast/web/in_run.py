"""``cast run --web``: the web view inside the orchestrator, beside the servers it runs.

Bound before anything starts (a taken port stops ``cast run`` with exit 2,
nothing started), attached once the servers are up under a reader identity the
orchestrator signs itself, told to stop watching after the components and
before the servers, closed last. It runs on threads of its own over gRPC, like
``cast web`` from another terminal: the orchestrator's event loop, which serves
the working memories, never waits for a browser.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from cast.auth import TokenSigner
from cast.client.credentials import ClientTls, TokenSource
from cast.core.records import Identity
from cast.errors import CastError
from cast.web.address import listening_line, parse_web_listen
from cast.web.server import WebServer
from cast.web.view import WEB_ID, WebView

__all__ = ["RunWeb"]


class RunWeb:
    """The web view of one ``cast run``: bound at construction, then :meth:`attach`, then :meth:`close`.

    ``notice`` must be callable from any thread.
    """

    def __init__(self, listen: str, notice: Callable[[str], None]) -> None:
        self._notice = notice
        self.server = WebServer(parse_web_listen(listen, "--web"), "--web")
        self._view: WebView | None = None
        self._lock = threading.Lock()

    @property
    def port(self) -> int:
        """The bound port."""
        return self.server.port

    def attach(self, endpoint: str, signer: TokenSigner, tls: ClientTls | None) -> None:
        """Show the system whose directory is at ``endpoint``; print where, and the login link (or why not).

        Blocking (it asks the servers): call it off the event loop that serves them.
        """
        # A reader with no expiry: the token never leaves this process, and the watches resume with it.
        tokens = TokenSource(signer.issue(Identity(WEB_ID, "", False)))
        line = listening_line(self.server.address, self.server.url)
        try:
            view = WebView(self.server, endpoint, tokens, tls, self._notice)
        except CastError as exc:
            self._notice(f"{line}, but it shows nothing: {exc.message}")
            return
        with self._lock:
            self._view = view
        self._notice(line)
        self._notice(f"open {view.access.login_link()} (the login link works once; the next is printed when used)")

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
