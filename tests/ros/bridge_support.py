"""Starting the ROS bridge in the tests, the generated entry types the test process decodes with, own ROS 2 messages."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from tests.conftest import ROOT, ServerHandle, run_to_end
from tests.ros.ros_env import HELPERS, ros1_python, ros2_python

# Own ROS 2 message packages, each built once per content (tests/ros/helpers/build_ros2_msgs.py).
ROS2_MSGS = ROOT / "build" / "ros2-msgs"

BRIDGE_CLASS = {2: "cast.bridges.ros.ros2:Ros2Bridge", 1: "cast.bridges.ros.ros1:Ros1Bridge"}

READING_MSG = """\
# A reading of a team's own sensor: a message package of the test's own, built with rosidl's generators.
uint8 LEVEL_LOW=0
uint8 LEVEL_HIGH=2
string UNIT="bar"
std_msgs/Header header
uint8 level
float64 value
int16[3] triple
string<=16 label
geometry_msgs/Point[<=4] points
float32[<=3] gains
uint8[] blob
uint8[4] code
int64 count
builtin_interfaces/Duration window
"""


def start_bridge(server: ServerHandle, component_id: str, sa: str, settings: dict[str, Any], env: dict[str, str],
                 log: Path, privileged: bool = True, overlay: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """The bridge as `cast run` starts it: its interpreter, the runner, the launch contract and CAST_ROS_BRIDGE.

    ``overlay``: what sourcing the setup.bash of a workspace with a team's own message packages sets
    (PYTHONPATH; for ROS 2 also LD_LIBRARY_PATH and AMENT_PREFIX_PATH), before the environment's own values.
    """
    ros = int(settings.get("version", 2))
    python = ros2_python() if ros == 2 else ros1_python()
    full = {**server.env(component_id, sa, privileged), **{k: v for k, v in env.items() if k.startswith(("ROS", "FAST",
            "RMW", "CMAKE", "PYTHONUNBUFFERED"))}, "CAST_ROS_BRIDGE": json.dumps(settings)}
    full.pop("PYTHONPATH", None)  # the bridge's interpreter has the cast package (editable): nothing of .venv's
    for key, value in (overlay or {}).items():
        full[key] = os.pathsep.join(p for p in (value, full.get(key, "")) if p)
    out = log.open("w")
    return subprocess.Popen([str(python), "-m", "cast.run", BRIDGE_CLASS[ros]], env=full, stdout=out,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def generate_types(out: Path, ros: int, *types: str, overlay: dict[str, str] | None = None) -> Path:
    """``cast ros-types`` with the ROS interpreter, then protoc for Python: the directory to put on sys.path.

    ``overlay``: as for :func:`start_bridge`, where the ROS interpreter finds a team's own messages.
    """
    python = ros2_python() if ros == 2 else ros1_python()
    protos = out / "protos"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    for key, value in (overlay or {}).items():
        env[key] = os.pathsep.join(p for p in (value, env.get(key, "")) if p)
    done = run_to_end([str(python), "-m", "cast.cli", "ros-types", "--ros", str(ros), "-q", *types, "-o", str(protos)],
                      "cast ros-types", 60, env=env)
    assert done.returncode == 0, done.stderr
    files = sorted(p.relative_to(protos).as_posix() for p in protos.rglob("*.proto"))
    python_out = out / "python"
    python_out.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{protos}", f"--python_out={python_out}", *files],
                   check=True)
    return python_out


def cast_test_msgs() -> dict[str, str]:
    """The test's own message package (cast_test_msgs/msg/Reading): the overlay that puts it on the ROS path.

    One definition for every test that uses it, so that all share one build (:func:`ros2_message_package`
    keeps only the newest content of a package).
    """
    return ros2_message_package("cast_test_msgs", {"Reading": READING_MSG})


def ros2_message_package(name: str, messages: dict[str, str]) -> dict[str, str]:
    """A ROS 2 message package ``name`` with ``messages`` (type name -> .msg text), built once for its content.

    Built by tests/ros/helpers/build_ros2_msgs.py with the ROS 2 interpreter (rosidl generators and gcc, as
    colcon would with ament_cmake) into build/ros2-msgs/<name>-<hash>, which is kept: a run after the first
    takes no time. The answer is the overlay that puts it on the ROS path (:func:`start_bridge`).
    """
    python = ros2_python()
    script = HELPERS / "build_ros2_msgs.py"
    key = hashlib.sha256(json.dumps([sorted(messages.items()), script.read_text(), str(python),
                                     (ROOT / "requirements-ros2.txt").read_text()]).encode()).hexdigest()[:12]
    prefix = ROS2_MSGS / f"{name}-{key}"
    overlay = prefix / "overlay.json"
    ROS2_MSGS.mkdir(parents=True, exist_ok=True)
    # Two pytest workers may need the package at once: the second waits for the first's build.
    with (ROS2_MSGS / f".{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not overlay.is_file():
            work = ROS2_MSGS / f".{name}-{key}-{os.getpid()}"
            shutil.rmtree(work, ignore_errors=True)
            source = work / "src" / name
            (source / "msg").mkdir(parents=True)
            for type_name, text in messages.items():
                (source / "msg" / f"{type_name}.msg").write_text(text)
            started = time.monotonic()
            # The prefix is final before it is built: its paths are what the overlay names. Builds of other
            # contents of the package are of no use any more.
            for old in ROS2_MSGS.glob(f"{name}-*"):
                shutil.rmtree(old, ignore_errors=True)
            env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
            done = run_to_end([str(python), str(script), str(source), str(prefix)], "build_ros2_msgs.py", 300, env=env)
            shutil.rmtree(work, ignore_errors=True)
            assert done.returncode == 0, f"building the ROS 2 message package {name}:\n{done.stdout}\n{done.stderr}"
            paths = json.loads(done.stdout.strip().splitlines()[-1])
            print(f"built the ROS 2 message package {name} in {time.monotonic() - started:.1f} s ({prefix})")
            overlay.write_text(json.dumps(paths))
        return dict(json.loads(overlay.read_text()))
