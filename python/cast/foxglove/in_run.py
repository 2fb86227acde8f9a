"""``cast run --foxglove``: the live view inside the orchestrator, beside the servers it runs.

The view is bound first (a taken port stops ``cast run`` with exit 2 before
anything starts), so it shows everything the components did; the steps are
those of every attached tool (:mod:`cast.attach`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from cast.attach import AttachedTool
from cast.client.credentials import ClientTls, TokenSource
from cast.foxglove.address import listening_line, parse_foxglove_listen
from cast.foxglove.sink import FoxgloveSink
from cast.foxglove.view import VIEW_ID, BackgroundView

__all__ = ["RunView"]


class RunView(AttachedTool):
    """The live view of one ``cast run``: bound at construction, then :meth:`attach`, then :meth:`close`."""

    tool_id = VIEW_ID

    def __init__(self, listen: str, notice: Callable[[str], None]) -> None:
        super().__init__(notice)
        address = parse_foxglove_listen(listen, "--foxglove")
        self.sink = FoxgloveSink(address, "cast run", notice, "--foxglove")
        self._view: BackgroundView | None = None
        self._lock = threading.Lock()

    @property
    def port(self) -> int:
        """The bound port."""
        return self.sink.port

    def _start(self, endpoint: str, tokens: TokenSource, tls: ClientTls | None) -> None:
        view = BackgroundView.start(self.sink, endpoint, tokens, tls, self._notice)
        with self._lock:
            self._view = view
        self._notice(listening_line(self.sink.address, self.sink.url))

    def _not_started(self, why: str) -> str:
        return f"{listening_line(self.sink.address, self.sink.url)}, but it shows nothing: {why}"

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
