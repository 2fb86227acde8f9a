"""Imports go down only, and every package has its place (docs/design.md, "Folders").

Every import of every module under python/cast (function-level ones too) is read from the source.
:data:`MAY_IMPORT` names, for each package and top-level module, the parts of ``cast`` it may import;
a package or module missing from it fails the test, so a new one must be placed. The core in
particular imports nothing but the errors it raises: no gRPC, no generated wire code.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

CAST = ROOT / "python" / "cast"

# The modules at the top that most parts share (errors, identities, the runtime directory, signals).
BASE = {"errors", "auth", "runtime_dir", "signals", "version", "v1"}

MAY_IMPORT: dict[str, set[str]] = {
    "errors": set(),
    "version": {"v1"},
    "runtime_dir": {"errors"},
    "signals": {"errors"},
    "v1": set(),  # the generated wire code
    "auth": {"core", "errors"},
    "core": {"errors"},  # plain Python: no gRPC, no wire code (also checked below)
    "wire": {"core", "errors", "v1"},  # wire code both sides share
    "config": {"core", "errors"},
    "client": {"core", "wire"} | BASE,
    "listen": {"errors"},
    "attach": {"core", "client"} | BASE,  # what the tools cast run attaches share
    # the server hosts in-process components (on the client library) and reads the configuration
    "server": {"core", "wire", "client", "config"} | BASE,
    "recording": {"core", "client", "attach"} | BASE,  # record, replay, info: tools on the client library
    "foxglove": {"core", "client", "attach", "listen", "recording"} | BASE,  # the recorder's channels, live
    "web": {"core", "wire", "client", "attach", "listen", "bridges"} | BASE,
    "bridges": {"core", "client", "config"} | BASE,  # the ROS bridge: a component, and its mapping model
    "export": {"config"} | BASE,  # cast export: the configuration only
    "experiments": BASE,  # cast sweep: runs `cast run` as a process, reads its summary
    "testing": {"core", "wire", "client", "server", "config"} | BASE,  # the kit: servers and clients for tests
    "orchestrator": {"core", "wire", "client", "config", "server", "attach", "recording", "foxglove", "web"}
    | BASE,
    "agent": {"core", "config", "orchestrator"} | BASE,  # beside the orchestrator: its launchers
    "cli": {"core", "wire", "client", "config", "server", "recording", "foxglove", "web", "bridges", "export",
            "experiments", "orchestrator", "agent", "attach", "listen"} | BASE,
    "run": {"client"},  # python -m cast.run: the Python runner
    "__init__": {"client", "core", "errors"},  # `import cast`: the client library's public names
}

CORE_FORBIDDEN = ("grpc", "grpc_health", "grpc_reflection")


def imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
    return found


def part_of(path: Path) -> str:
    """The package (or top-level module) a file of python/cast belongs to."""
    rel = path.relative_to(CAST).parts
    return rel[0] if len(rel) > 1 else rel[0].removesuffix(".py")


def sources() -> list[Path]:
    return sorted(p for p in CAST.rglob("*.py") if part_of(p) != "v1")


def test_every_package_and_module_has_a_place() -> None:
    # A folder counts once it holds a Python file (a renamed package leaves only __pycache__ behind).
    parts = {part_of(p) for p in sources()} | {p.name for p in CAST.iterdir() if p.is_dir() and p.name != "v1"
                                                 and not p.name.startswith("__") and any(p.rglob("*.py"))}
    assert parts - MAY_IMPORT.keys() == set(), "place these in MAY_IMPORT (and in docs/design.md, 'Folders')"


def test_each_part_imports_only_what_it_may() -> None:
    offending = []
    for path in sources():
        me = part_of(path)
        for line, name in imports(path):
            if name == "cast" and me not in ("bridges", "testing", "__init__"):
                offending.append(f"{path.relative_to(ROOT)}:{line}: imports cast (the client library's names)")
            if not name.startswith("cast."):
                continue
            other = name.split(".")[1]
            if other != me and other not in MAY_IMPORT[me]:
                offending.append(f"{path.relative_to(ROOT)}:{line}: {me} imports {name}")
    assert not offending, "\n".join(offending)


def test_the_core_imports_no_grpc() -> None:
    offending = [
        f"{path.relative_to(ROOT)}:{line}: imports {name}"
        for path in sorted((CAST / "core").glob("*.py"))
        for line, name in imports(path)
        if any(name == bad or name.startswith(bad + ".") for bad in CORE_FORBIDDEN)
    ]
    assert not offending, "\n".join(offending)


def test_the_check_reads_real_imports() -> None:
    # The scan itself must see what it looks for, or the tests above could never fail.
    found = imports(CAST / "server" / "working_memory.py")
    assert any(name == "grpc" for _, name in found) and any(name.startswith("cast.v1") for _, name in found)
    assert part_of(CAST / "server" / "working_memory.py") == "server" and part_of(CAST / "errors.py") == "errors"
