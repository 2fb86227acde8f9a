"""The orchestrator talks to agents through the generated stubs only: nothing under
python/cast/orchestrator imports cast.agent (the agent's own row is in tests/core/test_boundaries.py)."""

from __future__ import annotations

from tests.conftest import ROOT
from tests.core.test_boundaries import imports


def test_the_orchestrator_never_imports_the_agent() -> None:
    offending = [
        f"{path.relative_to(ROOT)}:{line}: imports {name}"
        for path in sorted((ROOT / "python" / "cast" / "orchestrator").glob("*.py"))
        for line, name in imports(path)
        if name == "cast.agent" or name.startswith("cast.agent.")
    ]
    assert not offending, "\n".join(offending)
