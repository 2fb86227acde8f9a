"""C++ and Java components built on the .proto files `cast ros-types` writes, as a team builds its own.

C++: the library `make cpp` built, installed with `cmake --install` to a
temporary prefix, and tests/ros/cpp built with ``find_package(cast)`` and
``cast_add_entry_types``. Java: tests/ros/java, a Maven project whose
protobuf-maven-plugin compiles the files (``protoSourceRoot``) against the
cast-client `make java` installed. A missing build or tool fails the test.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT, run_to_end
from tests.interop.cpp_support import cpp_bin_dir
from tests.ros.ros_env import ros1_python, ros2_python

CPP_BUILD = ROOT / "build" / "cpp"
# What each component uses, no more: protoc's C++ output is slow to compile on two cores.
# cast_test_msgs is the test's own package (bridge_support.cast_test_msgs), on the ROS path when generated.
CPP_TYPES = {2: ("sensor_msgs/msg/Image", "geometry_msgs/msg/PoseStamped", "cast_test_msgs/msg/Reading"),
             1: ("sensor_msgs/Image",)}
JAVA_TYPES = {2: ("sensor_msgs/msg/Image", "geometry_msgs/msg/PoseStamped", "cast_test_msgs/msg/Reading",
                  "geometry_msgs/msg/Twist"), 1: ()}


def _tool(name: str, hint: str) -> str:
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: {hint}")
    return found


def ros_protos(out: Path, types: dict[int, tuple[str, ...]], overlay: dict[str, str] | None = None) -> Path:
    """The .proto files of ``types`` (by ROS generation), written by `cast ros-types` into one directory.

    ``overlay``: what puts a team's own ROS 2 message packages on the ROS path (as sourcing its setup.bash would).
    """
    for ros, names in types.items():
        if not names:
            continue
        python = ros2_python() if ros == 2 else ros1_python()
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        for key, value in (overlay or {}).items() if ros == 2 else ():
            env[key] = os.pathsep.join(p for p in (value, env.get(key, "")) if p)
        done = run_to_end([str(python), "-m", "cast.cli", "ros-types", "--ros", str(ros), "-q", *names,
                           "-o", str(out)], "cast ros-types", 60, env=env)
        assert done.returncode == 0, done.stderr
    return out


def build_cpp(protos: Path, work: Path) -> Path:
    """tests/ros/cpp built against the installed library; the executable."""
    cmake = _tool("cmake", "run `make cpp` (it installs the build tools)")
    if not (CPP_BUILD / "CMakeCache.txt").is_file() or not (cpp_bin_dir()).is_dir():
        pytest.fail(f"the C++ library is not built ({CPP_BUILD}): run `make cpp` first")
    prefix = work / "prefix"
    for command, what in (
        ([cmake, "--install", str(CPP_BUILD), "--prefix", str(prefix)], "cmake --install"),
        ([cmake, "-S", str(ROOT / "tests" / "ros" / "cpp"), "-B", str(work / "build"), f"-DCMAKE_PREFIX_PATH={prefix}",
          f"-DROS_PROTOS={protos}", "-DCMAKE_BUILD_TYPE=Release"], "cmake (configure)"),
        ([cmake, "--build", str(work / "build"), "-j2"], "cmake --build"),
    ):
        done = run_to_end(command, what, 600)
        assert done.returncode == 0, f"{what}:\n{done.stdout}\n{done.stderr}"
    return work / "build" / "ros_entry_check"


@dataclass
class JavaBuild:
    """The built Java component: its classes and the class path it runs with."""

    classes: Path
    classpath: str

    def command(self) -> list[str]:
        """The Java runner on the component's class."""
        return [_tool("java", "run `make java`"), "-cp", f"{self.classes}:{self.classpath}", "cast.client.Runner",
                "cast.rostest.RosEntryCheck"]


def start_java(protos: Path, work: Path) -> tuple[subprocess.Popen[str], Path]:
    """Start building tests/ros/java with Maven (entry types from ``protos``); the process and the project."""
    mvn = _tool("mvn", "run `make java` (it installs a JDK and Maven)")
    project = work / "java"
    shutil.copytree(ROOT / "tests" / "ros" / "java", project)
    proc = subprocess.Popen([mvn, "-B", "-ntp", "-q", "package", f"-Dros.protos={protos}"], cwd=project,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc, project


def finish_java(proc: subprocess.Popen[str], project: Path) -> JavaBuild:
    """The Java build started by :func:`start_java`, once it is done."""
    try:
        out, _ = proc.communicate(timeout=600)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"mvn package did not end in 600 s:\n{out}") from None
    assert proc.returncode == 0, f"mvn package (run `make java` first: it installs cast-client):\n{out}"
    return JavaBuild(project / "target" / "classes", (project / "target" / "classpath.txt").read_text().strip())


def once_per_run(factory: pytest.TempPathFactory, name: str, make: Callable[[Path], dict[str, str]]) -> dict[str, str]:
    """What ``make(work)`` answers, made by the first pytest process of the run that asks, shared with the rest.

    The pytest-xdist workers of one run have their base temporary directories in one parent, which no
    other run uses: the build goes there, under a lock, so the second worker to need it waits for the
    first's build (or finds it done) rather than compiling it again on the same two cores. A build that
    failed records nothing: the next process to ask builds it again (and reports its own failure).
    """
    base = factory.getbasetemp()
    shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / f"once-{name}"
    shared.mkdir(exist_ok=True)
    record = shared / "made.json"
    with (shared / ".lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if record.is_file():
            return dict(json.loads(record.read_text()))
        work = shared / "work"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir()
        made = make(work)
        record.write_text(json.dumps(made))
        return made


def wait_ready(proc: subprocess.Popen[str]) -> None:
    """Read a component's output up to its ``{"ready": true}`` line; the runner's log lines may come first."""
    assert proc.stdout is not None
    seen = []
    for line in proc.stdout:
        if line.startswith("{") and json.loads(line) == {"ready": True}:
            return
        seen.append(line)
    raise AssertionError("the component ended before it was ready:\n" + "".join(seen))


def printed(out: str) -> list[dict[str, Any]]:
    """The JSON lines of a component's output, without the runner's log lines."""
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]
