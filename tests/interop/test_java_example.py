"""The Java component of docs/java.md: the page shows the example's files, and it builds and runs under `cast run`."""

from __future__ import annotations

import importlib
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from tests.conftest import VENV_BIN, maven
from tests.docs.pages import fenced, section, shown
from tests.interop.java_support import ROOT, cast_run, java_classpath

EXAMPLE = ROOT / "examples" / "java"
PAGE = "docs/java.md"


def blocks(lang: str) -> list[str]:
    return fenced(section(PAGE, "A project of your own: Maven"), lang)


def squeeze(text: str) -> str:
    return re.sub(r"\s+", " ", text).strip()


def test_page_shows_the_example_files() -> None:
    assert blocks("java") == [(EXAMPLE / "src/main/java/cast/examples/MyComponent.java").read_text(),
                              (EXAMPLE / "src/test/java/cast/examples/MyComponentTest.java").read_text()]
    assert blocks("proto") == [(EXAMPLE / "src/main/proto/greeting.proto").read_text()]
    assert blocks("yaml") == [shown("examples/java/system.yaml")]
    [pom_snippet] = blocks("xml")
    assert squeeze(pom_snippet) in squeeze((EXAMPLE / "pom.xml").read_text())
    assert "{language: java, kind: managed, class: cast.examples.MyComponent" in blocks("yaml")[0]


def test_the_example_builds_and_answers_greetings_under_cast_run(tmp_path: Path) -> None:
    java_classpath()  # the library must be built (and installed in ~/.m2) first: `make java`
    if shutil.which("mvn") is None:
        pytest.fail("mvn is not installed: the Java example is built with Maven")
    work = tmp_path / "example"
    shutil.copytree(EXAMPLE, work, ignore=shutil.ignore_patterns("target"))
    commands = blocks("sh")[-1].strip().splitlines()
    assert commands == ["make java", "cd examples/java && mvn -q package", "cast run system.yaml"]
    # `mvn package` runs the example's own test too (MyComponentTest, cast-testing): `cast` on PATH for it.
    env = {**os.environ, "PATH": f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    build = subprocess.run([*maven(), "-q", "package"], cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, f"mvn package failed:\n{build.stdout}\n{build.stderr}"
    assert (work / "target" / "classes" / "cast" / "examples" / "MyComponent.class").exists()

    # The Python side of the test uses the same entry type, generated from the same .proto.
    gen = tmp_path / "gen"
    gen.mkdir()
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{work / 'src/main/proto'}", f"--python_out={gen}",
                    "greeting.proto"], check=True)
    sys.path.insert(0, str(gen))
    try:
        greeting_pb2 = importlib.import_module("greeting_pb2")
    finally:
        sys.path.remove(str(gen))
    Greeting = greeting_pb2.Greeting

    import cast

    run = cast_run(work / "system.yaml", tmp_path / "runtime", work)
    py = None
    try:
        # "Connected" means registered; the callback exists once start() returned (state RUNNING).
        run.wait_for_component("answerer", "running", 30)
        py = run.act_as("greeter", "greetings")
        answered = threading.Event()
        py.on_change(cast.address_filter("reply-g1"), lambda change: answered.set())
        py.add("g1", Greeting(text="world", **{"from": "greeter"}))
        if not answered.wait(30):
            logs = "".join(p.read_text() for p in (tmp_path / "runtime" / "logs").glob("*.log"))
            raise AssertionError(f"no answer\n{run.output()}\n{run.cli('components').stdout}\n"
                                 f"{run.cli('tasks').stdout}\n{run.cli('ls').stdout}\nlogs:\n{logs}")
        reply = py.get_entry("reply-g1", Greeting)
        assert reply.value.text == "hello, world"
        assert reply.value.reply_to == "g1"
        assert reply.author == "answerer"
        # The Java client registered the Greeting schema: tools render its entries as JSON.
        shown = run.cli("get", "greetings", "reply-g1")
        assert shown.returncode == 0, shown.stderr
        assert "hello, world" in shown.stdout and "answerer" in shown.stdout, shown.stdout
    finally:
        if py is not None:
            py._cast_close()
        code = run.stop()
    assert code == 0, run.output()
