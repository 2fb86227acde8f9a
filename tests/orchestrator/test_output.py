"""The orchestrator's terminal output when the terminal goes away (its window closed)."""

from __future__ import annotations

import errno
import io

from rich.console import Console

from cast.orchestrator.output import Output


class _HungUp(io.StringIO):
    """A terminal whose window was closed: every write fails as a hung-up tty's does."""

    def __init__(self) -> None:
        super().__init__()
        self.writes = 0

    def write(self, text: str) -> int:
        self.writes += 1
        raise OSError(errno.EIO, "Input/output error")

    def isatty(self) -> bool:
        return True


def test_a_terminal_that_refuses_writes_is_dropped_and_nothing_fails() -> None:
    terminal = _HungUp()
    output = Output(Console(file=terminal, force_terminal=True), live_status=True)
    with output:  # the live status view's start writes too
        output.update_status("1 component running")
        output.component_line("camera", "frame 1")
        output.notice("stopping")
        output.show("the summary")
    assert terminal.writes >= 1
    assert output.console.file is not terminal  # from the first failure on, nothing more is written there
    tried = terminal.writes
    output.notice("once more")
    assert terminal.writes == tried
