"""The ROS side of the bridge's tests: the interpreters that have ROS, ROS 2 kept on loopback, roscore on a free port.

ROS runs in interpreters of its own (``make ros-deps``): ``.venv-ros2`` has the
ROS 2 wheels, ``.venv-ros1`` is Debian's Python with rospy. A test that needs
one fails (never skips) when it is missing. The test process itself needs no
ROS: it starts ROS nodes (tests/ros/helpers) and the bridge as processes, and
reads what they did through the working memories, as any component would.

ROS 2 discovery stays on this machine: ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``,
a Fast DDS profile that allows only 127.0.0.1 and shared memory
(configs/ros/fastdds-localhost.xml), and a ``ROS_DOMAIN_ID`` of this test run.
ROS 1: each roscore listens on 127.0.0.1 on a port that was free.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import time
import xmlrpc.client
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import ROOT, stop_process

ROS2_PYTHON = Path(os.environ.get("CAST_ROS2_PYTHON", ROOT / ".venv-ros2" / "bin" / "python"))
ROS1_PYTHON = Path(os.environ.get("CAST_ROS1_PYTHON", ROOT / ".venv-ros1" / "bin" / "python"))
FASTDDS_PROFILE = ROOT / "configs" / "ros" / "fastdds-localhost.xml"
HELPERS = ROOT / "tests" / "ros" / "helpers"
# image_publisher's nodelet description and library link, unpacked by `make ros1-deps`.
IMAGE_PUBLISHER_PREFIX = ROOT / "build" / "ros1" / "image_publisher" / "usr"
# One domain per test run (pytest's process): runs of other checkouts on this machine stay apart.
DOMAIN_ID = 1 + os.getpid() % 200


def _interpreter(path: Path, what: str) -> Path:
    if not os.access(path, os.X_OK):
        pytest.fail(f"no {what} interpreter at {path}: `make ros-deps` installs it (tests that need ROS fail "
                    f"rather than skip when it cannot be installed)")
    return path


def ros2_python() -> Path:
    """The interpreter with rclpy (fails the test when it is missing)."""
    return _interpreter(ROS2_PYTHON, "ROS 2 (rclpy)")


def ros1_python() -> Path:
    """The interpreter with rospy (fails the test when it is missing)."""
    return _interpreter(ROS1_PYTHON, "ROS 1 (rospy)")


def ros2_env(log_dir: Path, base: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a ROS 2 process of this test run: loopback only, this run's domain."""
    env = dict(base if base is not None else os.environ)
    env.update(
        ROS_DOMAIN_ID=str(DOMAIN_ID),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        FASTDDS_DEFAULT_PROFILES_FILE=str(FASTDDS_PROFILE),
        RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
        ROS_LOG_DIR=str(log_dir),
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_LOCALHOST_ONLY", None)  # superseded by the discovery range; both set is an error in Kilted
    return env


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class RosCore:
    """A roscore of one test on 127.0.0.1:port."""

    port: int
    home: Path
    process: subprocess.Popen[str] | None = None

    @property
    def uri(self) -> str:
        """Its ROS_MASTER_URI."""
        return f"http://127.0.0.1:{self.port}"

    def env(self, base: dict[str, str] | None = None) -> dict[str, str]:
        """The environment of a ROS 1 process that uses this master."""
        env = dict(base if base is not None else os.environ)
        env.update(ROS_MASTER_URI=self.uri, ROS_IP="127.0.0.1", ROS_HOME=str(self.home), PYTHONUNBUFFERED="1",
                   ROS_PACKAGE_PATH=str(IMAGE_PUBLISHER_PREFIX / "share"),
                   CMAKE_PREFIX_PATH=str(IMAGE_PUBLISHER_PREFIX))
        env.pop("ROS_HOSTNAME", None)
        return env

    def start(self) -> None:
        """Start roscore on its port and wait until the master answers."""
        self.home.mkdir(parents=True, exist_ok=True)
        self.process = subprocess.Popen(["roscore", "-p", str(self.port)], env=self.env(), text=True,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + 30
        master = xmlrpc.client.ServerProxy(self.uri)
        while True:
            try:
                code, _, _ = master.getSystemState("/test")
                if code == 1:
                    return
            except OSError:
                pass
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"roscore on port {self.port} did not start (exit {self.process.poll()})")
            time.sleep(0.1)

    def stop(self) -> None:
        """Stop roscore and the master and rosout it started (its process group)."""
        if self.process is not None and self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, 15)
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.process.pid, 9)
                self.process.wait()
        self.process = None


@contextlib.contextmanager
def roscore(home: Path) -> Iterator[RosCore]:
    """A roscore on 127.0.0.1 and a free port, stopped at the end."""
    if not _which("roscore"):
        pytest.fail("no roscore on PATH: `make ros-deps` installs Debian's ROS 1 (ros-core)")
    core = RosCore(free_port(), home)
    core.start()
    try:
        yield core
    finally:
        core.stop()


def _which(name: str) -> bool:
    return any(os.access(Path(d) / name, os.X_OK) for d in os.environ.get("PATH", "").split(os.pathsep) if d)


def helper(python: Path, script: str, *args: str, env: dict[str, str], log: Path) -> subprocess.Popen[str]:
    """Start a helper script of tests/ros/helpers with a ROS interpreter; its output goes to ``log``."""
    out = log.open("w")
    return subprocess.Popen([str(python), str(HELPERS / script), *args], env=env, stdout=out,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


__all__ = ["DOMAIN_ID", "FASTDDS_PROFILE", "HELPERS", "RosCore", "free_port", "helper", "ros1_python",
           "ros2_env", "ros2_python", "roscore", "stop_process"]
