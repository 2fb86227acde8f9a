"""M7: the C++ and Java clients, measured like the Python one (sequential Add; write -> event latency)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def run(workdir: Path, n: int, python_add_per_s: float, python_latency_p50: float) -> dict[str, Any]:
    """The M7 row; figures for each client library that is built."""
    return {
        "id": "M7",
        "what": "C++ and Java clients: sequential Add; write -> event latency to a watcher in the same language",
        "target": "Add calls/s >= the Python client's; latency p50 <= 1.2 x the Python client's",
        "figures": [
            {"name": "Python Add/s (reference)", "value": python_add_per_s},
            {"name": "Python latency p50 µs (reference)", "value": python_latency_p50},
        ],
        "met": False,
        "note": "C++ and Java benchmark clients not built yet",
    }
