"""System configuration: the YAML file that describes subarchitectures and components.

:func:`load_config` reads, substitutes variables, follows includes and
validates against the configuration's JSON Schema (``system.schema.json``) and
the rules a schema cannot say, raising :class:`ConfigError` with one line per
problem (file, line, key). ``cast check`` adds the orchestrator's preflight
(:func:`cast.orchestrator.preflight.preflight`: classes import, executables
exist) on top. This package depends on ``cast.core`` and nothing above it.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from cast.config import model
from cast.config.model import *  # noqa: F403  (the package re-exports the model's public names)
from cast.config.model import SystemConfig
from cast.config.problems import ConfigError, Position, Problem, Problems
from cast.config.source import load_tree
from cast.config.validate import build_config

__all__ = [
    *model.__all__,
    "ConfigError",
    "Position",
    "Problem",
    "Problems",
    "load_config",
    "parse_config",
    "read_config",
]


def read_config(
    path: str | os.PathLike[str],
    overrides: Mapping[str, str] | None = None,
    environ: Mapping[str, str] | None = None,
    text: str | None = None,
) -> tuple[SystemConfig | None, Problems]:
    """Read and validate a configuration; return it (None if unreadable) and every problem found."""
    tree = load_tree(path, overrides, environ, text)
    if not tree.readable:
        return None, tree.problems
    config = build_config(tree)
    return config, tree.problems


def load_config(
    path: str | os.PathLike[str],
    overrides: Mapping[str, str] | None = None,
    environ: Mapping[str, str] | None = None,
) -> SystemConfig:
    """Read and validate a configuration file; :class:`ConfigError` listing every problem if it has errors."""
    config, problems = read_config(path, overrides, environ)
    problems.raise_if_errors()
    assert config is not None
    return config


def parse_config(data: Any, source: str = "<config>") -> SystemConfig:
    """Validate already-parsed YAML data (a dict); positions refer to its YAML dump."""
    text = yaml.safe_dump(data, sort_keys=False)
    config, problems = read_config(Path(source), text=text)
    problems.raise_if_errors()
    assert config is not None
    return config
