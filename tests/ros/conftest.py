"""Fixtures of the ROS bridge's tests: the entry types generated once per session, a server, ROS 2's environment."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import ServerHandle, start_server
from tests.ros.bridge_support import cast_test_msgs, generate_types
from tests.ros.builds import CPP_TYPES, JAVA_TYPES, JavaBuild, build_cpp, finish_java, ros_protos, start_java
from tests.ros.ros_env import ros2_env

ROS_CONFIG = {"system": "ros-test", "subarchitectures": {"vision": {}, "motor": {}, "language": {}}}


@pytest.fixture(scope="session")
def ros2_types(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The standard ROS 2 message types as Python protobuf modules (``ros2.sensor_msgs.msg.image_pb2``)."""
    out = generate_types(tmp_path_factory.mktemp("ros2-types"), 2, "std_msgs", "geometry_msgs", "sensor_msgs")
    sys.path.insert(0, str(out))
    return out


@pytest.fixture(scope="session")
def ros1_types(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The standard ROS 1 message types as Python protobuf modules (``ros1.sensor_msgs.msg.image_pb2``)."""
    out = generate_types(tmp_path_factory.mktemp("ros1-types"), 1, "std_msgs", "geometry_msgs", "sensor_msgs")
    sys.path.insert(0, str(out))
    return out


@pytest.fixture
def ros_server(tmp_path: Path) -> Iterator[ServerHandle]:
    """A real `cast serve` on port 0 hosting vision, motor and language."""
    handle = start_server(tmp_path / "server", ROS_CONFIG)
    yield handle
    handle.stop()


@pytest.fixture
def ros2(tmp_path: Path) -> dict[str, str]:
    """The environment of this test's ROS 2 processes (loopback only, this run's domain)."""
    (tmp_path / "ros-logs").mkdir(exist_ok=True)
    return ros2_env(tmp_path / "ros-logs")


@pytest.fixture(scope="session")
def ros_builds(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, JavaBuild]:
    """The C++ and Java components of tests/ros built on `cast ros-types` output (once per session)."""
    work = tmp_path_factory.mktemp("ros-builds")
    overlay = cast_test_msgs()  # the test's own message package, decoded by both (built once, cached)
    java = start_java(ros_protos(work / "java-protos", JAVA_TYPES, overlay), work)  # on the other core, meanwhile
    try:
        cpp = build_cpp(ros_protos(work / "cpp-protos", CPP_TYPES, overlay), work / "cpp")
    finally:
        built = finish_java(*java)
    return cpp, built
