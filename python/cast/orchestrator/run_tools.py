"""The tools ``cast run`` can run beside its servers: the Foxglove live view, a recording, the web view.

Their steps in a run are those of :class:`cast.attach.AttachedTool`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from cast.attach import AttachedTool
from cast.foxglove.in_run import RunView
from cast.recording.in_run import RunRecording
from cast.web.in_run import RunWeb

__all__ = ["make_tools"]


def make_tools(foxglove: str | None, record: Path | None,
               notices: Callable[[str], Callable[[str], None]], web: str | None = None) -> list[AttachedTool]:
    """The tools asked for (``--foxglove``, ``--record``, ``--web``); ``notices(name)`` gives each its notice line."""
    tools: list[AttachedTool] = []
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
