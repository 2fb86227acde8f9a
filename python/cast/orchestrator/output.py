"""The orchestrator's terminal: component lines, notices, and the live status view.

On a terminal the status view stays at the bottom and component output
scrolls above it; elsewhere (a pipe, a CI log) every component line is printed
with its component's name in front, and notices start with ``cast:``.
"""

from __future__ import annotations

from types import TracebackType

from rich.console import Console, RenderableType
from rich.live import Live
from rich.markup import escape

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

    def known_components(self, ids: list[str]) -> None:
        """Align the name column to the longest id."""
        self._width = max([self._width, *(len(i) for i in ids)])

    def component_line(self, component_id: str, text: str) -> None:
        """One line of a component's output."""
        if self.quiet_components:
            return
        colour = self._colours.setdefault(component_id, _PALETTE[len(self._colours) % len(_PALETTE)])
        self.console.print(f"[{colour}]{escape(component_id):>{self._width}}[/] | {escape(text)}")

    def notice(self, text: str) -> None:
        """Something the orchestrator did or saw."""
        self.console.print(f"[bold]cast:[/] {escape(text)}")

    def show(self, renderable: RenderableType) -> None:
        """Print something once (the summary)."""
        self.console.print(renderable)

    def update_status(self, renderable: RenderableType) -> None:
        """Redraw the live status view (no-op without a terminal)."""
        if self._live is not None:
            self._live.update(renderable, refresh=True)

    def __enter__(self) -> Output:
        if self.live_status:
            self._live = Live(console=self.console, auto_refresh=False, transient=True, redirect_stdout=False,
                              redirect_stderr=False)
            self._live.__enter__()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._live is not None:
            self._live.__exit__(exc_type, exc, tb)
            self._live = None
