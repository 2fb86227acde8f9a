"""The C++ example of docs/cpp.md is the example's files, builds with exactly its CMake, and runs.

Also the demo with its C++ segmenter.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.docs.pages import fenced, section, shown
from tests.interop.cpp_support import ROOT, CppProcess, cpp_executable

PAGE = "docs/cpp.md"
SECTION = "A project of your own: CMake"
EXAMPLE = ROOT / "examples" / "cpp" / "hello"
CAST = str(Path(sys.executable).parent / "cast")


def block(lang: str, index: int = 0) -> str:
    found = fenced(section(PAGE, SECTION), lang)
    assert len(found) > index, f"no ```{lang} block number {index} in {PAGE}, {SECTION!r}"
    return str(found[index])


def clean_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    if "CAST_CPP_BIN_DIR" in os.environ:
        env["CAST_CPP_BIN_DIR"] = os.environ["CAST_CPP_BIN_DIR"]
    return env


def test_page_snippets_are_the_example_files() -> None:
    assert [block("cpp", i) for i in range(3)] == [(EXAMPLE / name).read_text()
                                                   for name in ("hello.h", "hello.cc", "hello_test.cc")]
    assert block("proto") == (EXAMPLE / "greeting.proto").read_text()
    assert block("cmake") == (EXAMPLE / "CMakeLists.txt").read_text()
    assert block("yaml") == shown("examples/cpp/hello/system.yaml")


def expected_lines() -> list[str]:
    return [re.sub(r":[0-9a-f]{6}:", ":X:", line.strip()) for line in block("text").strip().splitlines()]


def test_page_commands_run_the_example(tmp_path: Path) -> None:
    commands = block("sh").strip().splitlines()
    assert commands == ["make cpp", "cast run examples/cpp/hello/system.yaml --for 2"]
    cpp_executable("hello_cpp")  # `make cpp` ran before the tests (make test); fail, never skip, if not
    args = commands[1].split()[1:]
    out = subprocess.run(
        [CAST, *args, "--no-status", "--runtime-dir", str(tmp_path / "rt")],
        cwd=ROOT, env=clean_env(), capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    lines = [re.sub(r":[0-9a-f]{6}:", ":X:", line.strip()) for line in out.stdout.splitlines()
             if line.strip().startswith("hello |")]
    assert lines == expected_lines(), out.stdout
    assert "every component ran and stopped cleanly" in out.stdout


@pytest.mark.timeout(900)  # it builds the whole library from scratch: minutes on a busy 2-core machine
def test_the_example_builds_with_the_library_as_a_subdirectory(tmp_path: Path, server_factory: Any) -> None:
    """A user's project that builds the library from source: cpp_client and the example, each added as a
    subdirectory (against an installed library instead: tests/packaging/test_packages.py)."""
    cmake = shutil.which("cmake")
    assert cmake, "cmake is not installed: run `make cpp` (it installs the build tools)"
    shutil.copytree(EXAMPLE, tmp_path / "project" / "hello")
    (tmp_path / "project" / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.16)\nproject(robot LANGUAGES CXX)\n"
        f"add_subdirectory({(ROOT / 'cpp_client').as_posix()} cast)\nadd_subdirectory(hello)\n")
    build = tmp_path / "build"
    # No build type: no optimisation, which halves the compile; what is tested is that the tree builds
    # and links as a subdirectory, file by file as a project's default build compiles it (make cpp builds
    # the optimised library that the other tests run as a unity build, so both ways are built).
    configure = subprocess.run([cmake, "-S", str(tmp_path / "project"), "-B", str(build), "-DCMAKE_BUILD_TYPE="],
                               capture_output=True, text=True, timeout=300)
    assert configure.returncode == 0, configure.stdout + configure.stderr
    made = subprocess.run([cmake, "--build", str(build), "-j2", "--target", "hello_cpp"],
                          capture_output=True, text=True, timeout=900)
    assert made.returncode == 0, made.stdout[-4000:] + made.stderr[-4000:]
    binary = build / "hello" / "hello_cpp"
    assert binary.is_file()
    # Run the freshly built executable with the launch contract, as the orchestrator would.
    handle = server_factory({"system": "hello", "subarchitectures": {"greetings": {}}})
    proc = subprocess.run([str(binary)], env=handle.env("hello", "greetings", args={"count": 3}),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    got = [re.sub(r":[0-9a-f]{6}:", ":X:", line) for line in proc.stdout.strip().splitlines()]
    assert got == [line.split("| ", 1)[1] for line in expected_lines()]


def test_demo_runs_with_the_cpp_segmenter(tmp_path: Path) -> None:
    cpp_executable("segmenter")
    summary = tmp_path / "summary.json"
    out = subprocess.run(
        [CAST, "run", str(ROOT / "configs" / "demo.yaml"), "--set", "SEGMENTER_LANGUAGE=cpp", "--for", "6",
         "--no-status", "--runtime-dir", str(tmp_path / "rt"), "--summary-json", str(summary)],
        cwd=tmp_path, env=clean_env(), capture_output=True, text=True, timeout=180,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "segmenter | frame 1: new region obj-1 at x=-0.45" in out.stdout
    data = json.loads(summary.read_text())
    assert data["failures"] == []
    segmenter = next(c for c in data["components"] if c["id"] == "segmenter")
    assert segmenter["language"] == "cpp" and segmenter["sessions"] == 1
    vision = next(sa for sa in data["subarchitectures"] if sa["name"] == "vision")
    # The C++ regions were refined by the (Python) recognisers through the vision task manager.
    assert vision["types"].get("cast.examples.SceneObject", 0) >= 5
    assert vision["counters"]["completed"] >= 1


def test_cpp_segmenter_entries_are_what_the_python_recognisers_expect(server_factory: Any) -> None:
    """The segmenter's regions, read in Python with the demo's generated classes."""
    sys.path.insert(0, str(ROOT / "build" / "python-examples"))
    try:
        from castdemo.scene_pb2 import SceneObject  # generated by `make examples`
    finally:
        sys.path.pop(0)
    handle = server_factory({"system": "seg", "subarchitectures": {"vision": {}}})
    seg = CppProcess("segmenter", handle.env("segmenter", "vision", args={"objects": 3, "rate_hz": 50, "seed": 7}))
    py = handle.connect("reader", "vision")
    try:
        for _ in range(3):
            assert "new region" in seg.lines.get(timeout=30)
        regions = sorted((e.value for e in py.get_all(SceneObject)), key=lambda r: r.label)
        assert [r.label for r in regions] == ["obj-1", "obj-2", "obj-3"]
        assert [(r.x, r.y) for r in regions] == [(-0.45, 0.30), (-0.25, 0.55), (0.00, 0.40)]
        assert [r.corners for r in regions] == [3, 0, 4]  # cone, ball, cube
        assert all(0.05 <= r.size <= 0.09 and 0 <= r.red <= 1 for r in regions)
        seg.terminate()
        assert seg.wait(15) == 0, seg.output()
    finally:
        py._cast_close()
        seg.close()
