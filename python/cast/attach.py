"""A tool that ``cast run`` attaches beside its servers: the recording, the Foxglove view, the web view.

Each is made before anything starts (a taken port or an existing file ends the run at once, nothing
started), attached once the servers are up and before any component starts, under a reader identity
of its own that the orchestrator signs, told to stop watching after the components and before the
servers, and closed on every way out (``cast.orchestrator.run_tools``). They run on threads of their
own over gRPC, like the same tools run from another terminal: the orchestrator's event loop, which
serves the working memories, is never blocked by them.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

from cast.auth import TokenSigner
from cast.client.credentials import ClientTls, TokenSource
from cast.core.records import Identity
from cast.errors import CastError

__all__ = ["AttachedTool"]


class AttachedTool(ABC):
    """The steps of one tool in a run; ``notice`` (callable from any thread) says what a person should know."""

    tool_id = ""
    """The identity the tool reads under (``cast-record``, ``cast-foxglove``, ``cast-web``)."""

    def __init__(self, notice: Callable[[str], None]) -> None:
        self._notice = notice

    def attach(self, endpoint: str, signer: TokenSigner, tls: ClientTls | None) -> None:
        """Start on the system whose directory is at ``endpoint`` (blocking: call it off the event loop).

        A reader: privilege only widens writes, and the tools write nothing. No expiry: the token never
        leaves this process, and the tool resumes its watches with it after a reconnect.
        """
        tokens = TokenSource(signer.issue(Identity(self.tool_id, "", False)))
        try:
            self._start(endpoint, tokens, tls)
        except CastError as exc:
            self._notice(self._not_started(exc.message))

    @abstractmethod
    def _start(self, endpoint: str, tokens: TokenSource, tls: ClientTls | None) -> None:
        """Start the tool; CastError when it cannot reach the system."""

    @abstractmethod
    def _not_started(self, why: str) -> str:
        """What to say when :meth:`_start` could not reach the system."""

    @abstractmethod
    def stop_watching(self) -> None:
        """The components have stopped: stop watching (the servers still run)."""

    @abstractmethod
    def close(self) -> None:
        """Release everything (also on an error path, attached or not)."""
