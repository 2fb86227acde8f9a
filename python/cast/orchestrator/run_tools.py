"""The tools ``cast run`` can run beside its servers: the Foxglove live view, a recording, the web view.

Each is made before anything starts (so that a taken port or an existing file
ends the run at once), attached once the servers are up and before any
component starts, told to stop watching after the components and before the
servers, and closed on every way out. They run on threads of their own over
gRPC, like the same tools run from another terminal (``cast foxglove``,
``cast record``): the orchestrator's event loop, which serves the working
memories, is never blocked by them.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from cast.auth import TokenSigner
from cast.client.credentials import ClientTls
from cast.liveview.in_run import RunView
from cast.recording.in_run import RunRecording
from cast.web.in_run import RunWeb

__all__ = ["RunTool", "make_tools"]


class RunTool(Protocol):
    """A tool's steps in a run (each blocking: called off the event loop)."""

    def attach(self, endpoint: str, signer: TokenSigner, tls: ClientTls | None) -> None:
        """Start on the system whose directory is at ``endpoint``, under an identity signed with ``signer``."""

    def stop_watching(self) -> None:
        """The components have stopped: stop watching (the servers still run)."""

    def close(self) -> None:
        """Release everything (also on an error path, attached or not)."""


def make_tools(foxglove: str | None, record: Path | None,
               notices: Callable[[str], Callable[[str], None]], web: str | None = None) -> list[RunTool]:
    """The tools asked for (``--foxglove``, ``--record``, ``--web``); ``notices(name)`` gives each its notice line."""
    tools: list[RunTool] = []
    try:
        if foxglove is not None:
            tools.append(RunView(foxglove, notices("foxglove")))
        if record is not None:
            tools.append(RunRecording(record, notices("record")))
        if web is not None:
            tools.append(RunWeb(web, notices("web")))
    except BaseException:
        for tool in tools:
            tool.close()
        raise
    return tools
