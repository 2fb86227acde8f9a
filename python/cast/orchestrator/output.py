"""The orchestrator's terminal: component lines, notices, and the live status view.

On a terminal the status view stays at the bottom and component output
scrolls above it; elsewhere (a pipe, a CI log) every component line is printed
with its component's name in front, and notices start with ``cast:``. When the
terminal goes away (its window closed: SIGHUP, or a write that fails), nothing
more is shown and nothing fails for it; the logs and ``--summary-json`` are files
and carry on.
"""

from __future__ import annotations

import os
from types import TracebackType

from rich.console import Console, RenderableType
from rich.live import Live
from rich.markup import escape

from cast.signals import descriptors_on, silence, terminal_descriptors

__all__ = ["Output"]

_PALETTE = ("cyan", "magenta", "green", "yellow", "blue", "bright_red", "bright_cyan", "bright_magenta",
            "bright_green", "bright_blue")


class Output:
    """Where everything the orchestrator shows goes."""

    def __init__(
        self, console: Console | None = None, live_status: bool = True, quiet_components: bool = False
    ) -> None:
        self.console = console or Console(highlight=False, soft_wrap=True)
        self.live_status = live_status and self.console.is_terminal
        self.quiet_components = quiet_components
        self._colours: dict[str, str] = {}
        self._width = 10
        self._live: Live | None = None
        # Known now: once the terminal has hung up, asking it whether it is one fails.
        self._terminal_fds = _terminal_fds(self.console)

    def known_components(self, ids: list[str]) -> None:
        """Align the name column to the longest id."""
        self._width = max([self._width, *(len(i) for i in ids)])

    def component_line(self, component_id: str, text: str) -> None:
        """One line of a component's output."""
        if self.quiet_components:
            return
        colour = self._colours.setdefault(component_id, _PALETTE[len(self._colours) % len(_PALETTE)])
        self._print(f"[{colour}]{escape(component_id):>{self._width}}[/] | {escape(text)}")

    def notice(self, text: str) -> None:
        """Something the orchestrator did or saw."""
        self._print(f"[bold]cast:[/] {escape(text)}")

    def show(self, renderable: RenderableType) -> None:
        """Print something once (the summary)."""
        self._print(renderable)

    def update_status(self, renderable: RenderableType) -> None:
        """Redraw the live status view (no-op without a terminal)."""
        if self._live is not None:
            try:
                self._live.update(renderable, refresh=True)
            except OSError:
                self.hang_up()

    def hang_up(self) -> None:
        """The terminal is gone: show nothing from now on, and let no write fail for it.

        The console's terminal (and standard error, when it is the same terminal) now points at
        /dev/null, so that neither this console nor what Python still buffers for it (flushed at
        exit) fails later.
        """
        self._live = None  # its clean-up would write to the terminal
        silence(self._terminal_fds)
        self.console = Console(file=open(os.devnull, "w"), highlight=False, soft_wrap=True)

    def _print(self, renderable: RenderableType) -> None:
        try:
            self.console.print(renderable)
        except OSError:
            # A window closed before its SIGHUP arrived: its terminal refuses writes (EIO).
            self.hang_up()

    def __enter__(self) -> Output:
        if self.live_status:
            self._live = Live(console=self.console, auto_refresh=False, transient=True, redirect_stdout=False,
                              redirect_stderr=False)
            try:
                self._live.__enter__()
            except OSError:
                self.hang_up()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._live is not None:
            try:
                self._live.__exit__(exc_type, exc, tb)
            except OSError:
                self.hang_up()
            self._live = None


def _terminal_fds(console: Console) -> list[int]:
    """Those of standard output and error that are the console's terminal."""
    try:
        own = os.fstat(console.file.fileno())
    except (OSError, ValueError):  # not a file of the OS (a test's buffer)
        return []
    return descriptors_on(own, terminal_descriptors())
