"""The README's quick start works as written (its commands run here, with a free port).

The per-language pages (docs/python.md, docs/cpp.md, docs/java.md), the scripts snippet among them, are
run by tests/docs/test_docs_examples.py.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from tests.conftest import ROOT

README = (ROOT / "README.md").read_text()


def section(title: str) -> str:
    start = README.index(f"## {title}\n")
    end = README.find("\n## ", start + 1)
    return README[start : end if end != -1 else None]


def blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, re.S)


def test_quickstart_component_in_readme_is_the_example_file() -> None:
    snippet = blocks(section("Quick start"), "python")[0]
    assert snippet.strip() in (ROOT / "examples" / "quickstart" / "hello.py").read_text()


def test_quickstart_commands_run_as_written(tmp_path: Path) -> None:
    commands = blocks(section("Quick start"), "sh")[0].strip().splitlines()
    assert commands[0] == "cast serve system.yaml --listen 127.0.0.1:50051 &"
    work = tmp_path / "quickstart"
    shutil.copytree(ROOT / "examples" / "quickstart", work)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    env.pop("CAST_SECRET", None)
    server = subprocess.Popen(
        commands[0].rstrip(" &").replace("50051", "0").split(),
        cwd=work,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert server.stdout is not None
        first = server.stdout.readline().strip()
        assert re.fullmatch(r"listening on 127\.0\.0\.1:\d+", first), first
        port = first.rsplit(":", 1)[1]
        assert (work / ".cast" / "secret").exists()
        script = "\n".join(["set -e", *(c.replace("50051", port) for c in commands[1:])])
        out = subprocess.run(["bash", "-c", script], cwd=work, env=env, capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        lines = out.stdout.strip().splitlines()
        assert len(lines) == 3
        for i, line in enumerate(lines):
            assert re.fullmatch(rf"ADD hello:[0-9a-f]+:{i + 1} \(revision {i + 1}\): hello {i}", line), line
        expected = blocks(section("Quick start"), "text")[0].strip().splitlines()
        assert [re.sub(r":[0-9a-f]{6}:", ":X:", e) for e in expected] == [
            re.sub(r":[0-9a-f]{6}:", ":X:", line) for line in lines
        ]
    finally:
        server.terminate()
        server.wait(10)


def test_several_machines_configuration_checks(tmp_path: Path) -> None:
    yaml_text = blocks(section("Several machines: `cast agent`"), "yaml")[0]
    config = tmp_path / "robot.yaml"
    config.write_text(yaml_text)
    cast = str(Path(sys.executable).parent / "cast")
    out = subprocess.run([cast, "check", str(config)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "hosts: local (0 components), workstation (1 component)" in out.stdout, out.stdout
