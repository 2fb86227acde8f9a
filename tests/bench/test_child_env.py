"""The Python processes a benchmark starts import the same ``cast`` package as the benchmark itself.

``make bench`` runs from ``.venv-mypyc`` and its report names the compiled
build: a watcher process that put the tree's ``python/`` in front of its import
path would run the pure package instead, and its row would measure another
build than the header says.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from bench.harness import ROOT

PARENT = """
import subprocess, sys
import cast
from bench.harness import PYTHON, child_env
child = subprocess.run([PYTHON, "-c", "import cast; print(cast.__file__)"], env=child_env({"CAST_ENDPOINT": "x"}),
                       capture_output=True, text=True, check=True, cwd=sys.argv[1])
print(cast.__file__)
print(child.stdout.strip())
"""


def test_a_child_imports_the_cast_package_its_benchmark_imports(tmp_path: Path) -> None:
    # A stand-in for an installed build: a package named cast that only this parent's import path holds.
    installed = tmp_path / "site"
    (installed / "cast").mkdir(parents=True)
    (installed / "cast" / "__init__.py").write_text("")
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(installed), str(ROOT)])}
    out = subprocess.run([sys.executable, "-c", PARENT, str(elsewhere)], env=env, capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout.split()
    assert out == [str(installed / "cast" / "__init__.py")] * 2


def test_no_benchmark_puts_a_path_of_its_own_in_front_of_a_childs_imports() -> None:
    offenders = [p.name for p in sorted((ROOT / "bench").glob("*.py")) if '"PYTHONPATH":' in p.read_text()]
    assert offenders == [], f"{offenders} set PYTHONPATH for a child: use bench.harness.child_env"
