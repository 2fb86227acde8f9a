"""The core knows nothing above it: no gRPC, no generated wire code, no server, client or tool.
And the packages above it import downward only: core; then config and client; then server and
recording (and the live view beside it); then orchestrator; then cli (docs/design.md, "Folders").

Every import in every module under python/cast/core (function-level ones too) is
read from the source; the allowed packages are the standard library, protobuf's
runtime (descriptors and messages, for schemas) and the core itself, with the
errors it raises.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

CORE = ROOT / "python" / "cast" / "core"
FORBIDDEN = ("grpc", "grpc_health", "grpc_reflection", "cast.v1", "cast.server", "cast.client",
             "cast.cli", "cast.orchestrator", "cast.config", "cast.auth", "cast.recording", "cast.liveview")


def imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
    return found


def test_the_core_imports_nothing_above_it() -> None:
    offending = [
        f"{path.relative_to(ROOT)}:{line}: imports {name}"
        for path in sorted(CORE.glob("*.py"))
        for line, name in imports(path)
        if any(name == bad or name.startswith(bad + ".") for bad in FORBIDDEN)
    ]
    assert not offending, "\n".join(offending)


# What each package may not import: everything above it in the layering.
ABOVE = {
    "config": ("cast.client", "cast.server", "cast.orchestrator", "cast.cli", "cast.recording", "cast.liveview"),
    "client": ("cast.config", "cast.server", "cast.orchestrator", "cast.cli", "cast.recording", "cast.liveview"),
    # beside the server: a client-side tool (record, replay, info) on the client library only
    "recording": ("cast.config", "cast.server", "cast.orchestrator", "cast.agent", "cast.cli", "cast.liveview"),
    # the live view (cast foxglove, cast run --foxglove): the recorder's loop feeding a Foxglove server
    "liveview": ("cast.config", "cast.server", "cast.orchestrator", "cast.agent", "cast.cli"),
    "server": ("cast.orchestrator", "cast.cli", "cast.recording", "cast.liveview"),
    "orchestrator": ("cast.cli",),
    "agent": ("cast.client", "cast.server", "cast.cli"),  # beside the orchestrator: launchers and processes only
    # cast sweep's planning, report and plots: it runs `cast run` as a process, and reads its summary
    "experiments": ("cast.client", "cast.server", "cast.orchestrator", "cast.agent", "cast.cli", "cast.recording",
                    "cast.liveview"),
    # the ROS bridge: a component on the client library (and the configuration's mapping model)
    "bridges": ("cast.server", "cast.orchestrator", "cast.agent", "cast.cli", "cast.recording", "cast.liveview",
                "cast.web", "cast.experiments", "cast.export"),
    # the test kit: servers and clients in the test's process, `cast serve` and `cast run` as processes
    "testing": ("cast.orchestrator", "cast.agent", "cast.cli", "cast.recording", "cast.liveview", "cast.web",
                "cast.experiments", "cast.export"),
}


def test_each_package_imports_only_those_below_it() -> None:
    offending = [
        f"{path.relative_to(ROOT)}:{line}: imports {name}"
        for package, above in ABOVE.items()
        for path in sorted((ROOT / "python" / "cast" / package).rglob("*.py"))
        for line, name in imports(path)
        if any(name == bad or name.startswith(bad + ".") for bad in above)
    ]
    assert not offending, "\n".join(offending)


def test_the_check_reads_real_imports() -> None:
    # The scan itself must see what it looks for, or the test above could never fail.
    found = imports(ROOT / "python" / "cast" / "server" / "working_memory.py")
    assert any(name == "grpc" for _, name in found) and any(name.startswith("cast.v1") for _, name in found)
