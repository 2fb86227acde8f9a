"""Starting the ROS bridge in the tests, and the generated entry types the test process decodes with."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from tests.conftest import ServerHandle, run_to_end
from tests.ros.ros_env import ros1_python, ros2_python

BRIDGE_CLASS = {2: "cast.bridges.ros.ros2:Ros2Bridge", 1: "cast.bridges.ros.ros1:Ros1Bridge"}


def start_bridge(server: ServerHandle, component_id: str, sa: str, settings: dict[str, Any], env: dict[str, str],
                 log: Path, privileged: bool = True, python_path: str = "") -> subprocess.Popen[str]:
    """The bridge as `cast run` starts it: its interpreter, the runner, the launch contract and CAST_ROS_BRIDGE.

    ``python_path``: where a team's own message packages are (what sourcing its workspace's setup.bash puts
    on PYTHONPATH).
    """
    ros = int(settings.get("version", 2))
    python = ros2_python() if ros == 2 else ros1_python()
    full = {**server.env(component_id, sa, privileged), **{k: v for k, v in env.items() if k.startswith(("ROS", "FAST",
            "RMW", "CMAKE", "PYTHONUNBUFFERED"))}, "CAST_ROS_BRIDGE": json.dumps(settings)}
    full.pop("PYTHONPATH", None)  # the bridge's interpreter has the cast package (editable): nothing of .venv's
    if python_path:
        full["PYTHONPATH"] = python_path
    out = log.open("w")
    return subprocess.Popen([str(python), "-m", "cast.run", BRIDGE_CLASS[ros]], env=full, stdout=out,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def generate_types(out: Path, ros: int, *types: str) -> Path:
    """``cast ros-types`` with the ROS interpreter, then protoc for Python: the directory to put on sys.path."""
    python = ros2_python() if ros == 2 else ros1_python()
    protos = out / "protos"
    done = run_to_end([str(python), "-m", "cast.cli", "ros-types", "--ros", str(ros), "-q", *types, "-o", str(protos)],
                      "cast ros-types", 60)
    assert done.returncode == 0, done.stderr
    files = sorted(p.relative_to(protos).as_posix() for p in protos.rglob("*.proto"))
    python_out = out / "python"
    python_out.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{protos}", f"--python_out={python_out}", *files],
                   check=True)
    return python_out
