"""Figures measured by the reliability tests, collected for docs/reliability.md.

Each test that measures something calls :func:`record`; the figures of the
last run are in ``build/reliability-figures.json`` (``build/reliability-figures-soak.json`` for
``make soak``), one key per measurement.
"""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any

_BUILD = Path(__file__).resolve().parents[2] / "build"
_NAME = "reliability-figures-soak.json" if os.environ.get("CAST_SOAK") == "1" else "reliability-figures.json"
FIGURES = _BUILD / _NAME
_lock = threading.Lock()


def record(name: str, values: dict[str, Any]) -> None:
    """Store one measurement (replacing the last run's of the same name)."""
    with _lock:
        FIGURES.parent.mkdir(parents=True, exist_ok=True)
        try:
            data = json.loads(FIGURES.read_text())
        except (OSError, ValueError):
            data = {}
        data[name] = values
        tmp = FIGURES.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True))
        tmp.replace(FIGURES)


def soak() -> bool:
    """Whether the long variants run (``make soak`` sets CAST_SOAK=1)."""
    return os.environ.get("CAST_SOAK") == "1"
