"""``cast run --foxglove``: the live view inside the orchestrator, beside the servers it runs.

The orchestrator binds the view first (so a taken port stops ``cast run``
with exit 2 before anything starts), attaches it once the servers are up,
under a reader identity it signs itself, and stops it after the components and
before the servers, so the view shows everything the components did. The
view runs on its own thread over gRPC, like any tool: the orchestrator's
event loop, which serves the working memories, is never blocked by it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from cast.auth import TokenSigner
from cast.client.credentials import ClientTls, TokenSource
from cast.core.records import Identity
from cast.errors import CastError
from cast.liveview.sink import FoxgloveSink, listening_line, parse_listen
from cast.liveview.view import VIEW_ID, BackgroundView

__all__ = ["RunView"]


class RunView:
    """The live view of one ``cast run``: bound at construction, then :meth:`attach`, then :meth:`close`.

    ``notice`` must be callable from any thread (the view's notes come from its own).
    """

    def __init__(self, listen: str, notice: Callable[[str], None]) -> None:
        self._notice = notice
        address = parse_listen(listen, "--foxglove")
        self.sink = FoxgloveSink(address, "cast run", notice, "--foxglove")
        self._view: BackgroundView | None = None
        self._lock = threading.Lock()

    @property
    def port(self) -> int:
        """The bound port."""
        return self.sink.port

    def attach(self, endpoint: str, signer: TokenSigner, tls: ClientTls | None) -> None:
        """Show the system whose directory is at ``endpoint``; say where the view listens (or why it shows nothing).

        Blocking (it asks the servers): call it off the event loop that serves them.
        """
        # A reader: privilege only widens writes, and the view writes nothing. No expiry: the token never
        # leaves this process, and the view resumes its watches after a reconnect with it.
        tokens = TokenSource(signer.issue(Identity(VIEW_ID, "", False)))
        line = listening_line(self.sink.address, self.sink.url)
        try:
            view = BackgroundView.start(self.sink, endpoint, tokens, tls, self._notice)
        except CastError as exc:
            self._notice(f"{line}, but it shows nothing: {exc.message}")
            return
        with self._lock:
            self._view = view
        self._notice(line)

    def stop_watching(self) -> None:
        """End the watches (before the servers stop); the clients stay connected until :meth:`close`."""
        with self._lock:
            view, self._view = self._view, None
        if view is not None:
            view.stop()
            if view.error is not None:
                self._notice(f"the live view failed: {view.error}")

    def close(self) -> None:
        """End the watches if still running, disconnect the clients, release the port."""
        self.stop_watching()
        self.sink.close()
