"""Configuration problems: each names the file, the line and the key, and says what to do."""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from dataclasses import dataclass, field

from cast.errors import InvalidArgumentError

__all__ = ["ConfigError", "Position", "Problem", "Problems", "closest", "did_you_mean"]


@dataclass(frozen=True)
class Position:
    """Where something is written: file and 1-based line and column."""

    file: str
    line: int = 0
    column: int = 0

    def __str__(self) -> str:
        return f"{self.file}:{self.line}" if self.line else self.file


@dataclass(frozen=True)
class Problem:
    """One thing wrong (or, with ``warning``, doubtful) in a configuration."""

    position: Position
    key: str
    message: str
    warning: bool = False

    def __str__(self) -> str:
        kind = "warning" if self.warning else "error"
        where = f" {self.key}:" if self.key else ""
        return f"{self.position}: {kind}:{where} {self.message}"


class ConfigError(InvalidArgumentError):
    """A configuration with errors; ``problems`` lists every one (warnings included)."""

    def __init__(self, problems: Iterable[Problem] | str) -> None:
        if isinstance(problems, str):
            problems = [Problem(Position("<config>"), "", problems)]
        self.problems = list(problems)
        errors = [p for p in self.problems if not p.warning]
        count = f"{len(errors)} error{'s' if len(errors) != 1 else ''}"
        super().__init__("\n".join([*(str(p) for p in self.problems), f"configuration has {count}"]))


@dataclass
class Problems:
    """Collects problems so that a check reports all of them, not just the first."""

    items: list[Problem] = field(default_factory=list)

    def error(self, position: Position, key: str, message: str) -> None:
        """Record an error."""
        self.items.append(Problem(position, key, message))

    def warn(self, position: Position, key: str, message: str) -> None:
        """Record a warning (reported, but does not make the configuration invalid)."""
        self.items.append(Problem(position, key, message, warning=True))

    @property
    def errors(self) -> list[Problem]:
        """The problems that are errors."""
        return [p for p in self.items if not p.warning]

    @property
    def warnings(self) -> list[Problem]:
        """The problems that are warnings."""
        return [p for p in self.items if p.warning]

    def raise_if_errors(self) -> None:
        """Raise :class:`ConfigError` listing every problem if any is an error."""
        if self.errors:
            raise ConfigError(sorted(self.items, key=lambda p: (p.position.file, p.position.line)))


def did_you_mean(word: str, allowed: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for a close match, else the list of allowed words."""
    choices = sorted(allowed)
    close = difflib.get_close_matches(word, choices, n=1, cutoff=0.6)
    if close:
        return f" (did you mean '{close[0]}'?)"
    return f" (allowed: {', '.join(choices)})" if choices else ""


def closest(word: str, allowed: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for a close match, else nothing."""
    close = difflib.get_close_matches(word, sorted(allowed), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""
