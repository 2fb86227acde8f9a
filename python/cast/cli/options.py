"""Options shared by several commands."""

from __future__ import annotations

from collections.abc import Sequence

from cast.errors import InvalidArgumentError

__all__ = ["parse_sets"]


def parse_sets(items: Sequence[str] | None) -> dict[str, str]:
    """``--set NAME=VALUE`` options as a mapping; InvalidArgumentError for a malformed one."""
    out: dict[str, str] = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise InvalidArgumentError(f"--set takes NAME=VALUE, got '{item}'")
        out[name] = value
    return out
