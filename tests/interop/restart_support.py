"""What the C++ and Java reliability tests share: the restartable system's configuration and a
writer that rides out a server restart."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter

import cast
from tests.reliability.conftest import write_config


def restart_config(tmp: Path, persistence: bool) -> Path:
    """A vision + language system, journaled (durability batch) when ``persistence``."""
    config: dict[str, Any] = {"system": "rc", "subarchitectures": {"vision": {}, "language": {}}}
    if persistence:
        config["persistence"] = {"path": str(tmp / "wm.db"), "durability": "batch"}
    return write_config(tmp / "system.yaml", config)


def write_until(c: Any, prefix: str, n: int) -> None:
    """Write n entries, retrying those refused while the server is away."""
    for i in range(n):
        while True:
            try:
                c.add(f"{prefix}-{i}", Counter(value=i))
                break
            except cast.UnavailableError:
                time.sleep(0.05)
            except cast.AlreadyExistsError:
                break  # applied before the connection broke, acknowledgement lost
