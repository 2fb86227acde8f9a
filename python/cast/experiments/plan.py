"""What a sweep runs: every combination of the varied variables and task-manager policies.

``--vary NAME=a,b,c`` sets a configuration variable (as ``cast run --set``);
``--policy SA=fifo,priority`` replaces one SA's task-manager policy. A variant
is one combination; the sweep runs each ``repeat`` times. A policy is changed
with a small overlay file that includes the configuration and sets the policy,
so the user's file is never edited (includes merge mappings key by key, and
the including file wins: docs/configuration.md).
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cast.errors import InvalidArgumentError

__all__ = ["Variant", "parse_axes", "variants", "write_overlay"]

_NAME_CHARS = set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_")


@dataclass(frozen=True)
class Variant:
    """One combination: variable values and SA policies."""

    sets: tuple[tuple[str, str], ...] = ()
    policies: tuple[tuple[str, str], ...] = ()
    label: str = field(default="", compare=False)

    @property
    def name(self) -> str:
        """``NAME=value,SA:policy`` (``default`` with nothing varied): how tables and files name it."""
        parts = [f"{k}={v}" for k, v in self.sets] + [f"{sa}:{p}" for sa, p in self.policies]
        return ",".join(parts) or "default"

    @property
    def slug(self) -> str:
        """The name as a file name."""
        return "".join(c if c.isalnum() or c in "-_.=" else "_" for c in self.name.replace(":", "="))

    def to_json(self) -> dict[str, object]:
        """The variant as results.json stores it."""
        return {"name": self.name, "sets": dict(self.sets), "policies": dict(self.policies)}


def parse_axes(items: Sequence[str], option: str) -> list[tuple[str, list[str]]]:
    """``NAME=a,b,c`` items as (NAME, [a, b, c]); InvalidArgumentError naming the option and the item."""
    axes: list[tuple[str, list[str]]] = []
    for item in items:
        name, sep, values = item.partition("=")
        choices = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not name or not choices:
            raise InvalidArgumentError(f"{option} {item!r}: write NAME=value1,value2 (at least one value)")
        if not set(name) <= _NAME_CHARS:
            raise InvalidArgumentError(f"{option} {item!r}: '{name}' is not a name (letters, digits and _ only)")
        if any(name == seen for seen, _ in axes):
            raise InvalidArgumentError(f"{option} {name} is given twice: give every value in one {option}")
        if len(set(choices)) != len(choices):
            raise InvalidArgumentError(f"{option} {item!r}: a value is listed twice")
        axes.append((name, choices))
    return axes


def variants(vary: Sequence[tuple[str, list[str]]], policy: Sequence[tuple[str, list[str]]]) -> list[Variant]:
    """Every combination, in the order the options were given (the first varies slowest)."""
    names = [("set", n) for n, _ in vary] + [("policy", sa) for sa, _ in policy]
    out: list[Variant] = []
    for combo in itertools.product(*[values for _, values in [*vary, *policy]]):
        chosen = list(zip(names, combo, strict=True))
        out.append(Variant(tuple((n, v) for (kind, n), v in chosen if kind == "set"),
                           tuple((n, v) for (kind, n), v in chosen if kind == "policy")))
    return out


def write_overlay(config: Path, variant: Variant, directory: Path) -> Path:
    """The file to run for ``variant``: ``config`` itself, or an overlay setting its SA policies."""
    if not variant.policies:
        return config
    directory.mkdir(parents=True, exist_ok=True)
    overlay = directory / f"{variant.slug}.yaml"
    # JSON is YAML: the overlay includes the user's file by absolute path and changes only the policies.
    overlay.write_text(json.dumps({
        "include": str(config.resolve()),
        "subarchitectures": {sa: {"task_manager": {"policy": p}} for sa, p in variant.policies},
    }, indent=2) + "\n")
    return overlay
