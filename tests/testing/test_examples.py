"""The quick start's own tests (examples/quickstart/test_hello.py) pass with the kit's pytest plugin.

They run as a team's repository runs them: pytest in the example's directory, the fixture coming
from the installed package's plugin (its pytest11 entry point), nothing of this suite's conftest.
The C++ example's test runs under ctest (make test-cpp) and the Java example's under Maven
(tests/interop/test_java_example.py, tests/packaging).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from tests.conftest import ROOT


def test_the_quick_start_tests_pass_with_the_plugin(tmp_path: Path) -> None:
    work = tmp_path / "quickstart"
    shutil.copytree(ROOT / "examples" / "quickstart", work)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CAST_", "PYTEST_", "PYTHONPATH"))}
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"], cwd=work, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "2 passed" in done.stdout, done.stdout
