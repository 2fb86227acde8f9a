"""The source tree holds sources: nothing compiled beside them."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_no_compiled_module_shadows_a_source_in_the_tree() -> None:
    # A mypyc build in place would put extension modules beside the sources; Python imports those first, so
    # an edited .py would silently not run. The compiled build goes into .venv-mypyc (make mypyc) instead.
    found = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "python" / "cast").rglob("*.so"))
    assert not found, f"compiled modules in the tree shadow their sources: {found}; delete them"
