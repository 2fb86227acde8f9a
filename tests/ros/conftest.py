"""Fixtures of the ROS bridge's tests: the entry types generated once per session, a server, ROS 2's environment."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import ServerHandle, start_server
from tests.ros.bridge_support import cast_test_msgs, generate_types
from tests.ros.builds import (
    CPP_TYPES,
    JAVA_TYPES,
    JavaBuild,
    build_cpp,
    finish_java,
    once_per_run,
    ros_protos,
    start_java,
)
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
def ros_cpp_build(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The C++ component of tests/ros built on `cast ros-types` output: its executable (once per run)."""

    def make(work: Path) -> dict[str, str]:
        # cast_test_msgs: the test's own message package, decoded by both components (built once, cached).
        protos = ros_protos(work / "protos", CPP_TYPES, cast_test_msgs())
        return {"executable": str(build_cpp(protos, work / "cpp"))}

    return Path(once_per_run(tmp_path_factory, "ros-cpp", make)["executable"])


@pytest.fixture(scope="session")
def ros_java_build(tmp_path_factory: pytest.TempPathFactory) -> JavaBuild:
    """The Java component of tests/ros built on `cast ros-types` output (once per run)."""

    def make(work: Path) -> dict[str, str]:
        built = finish_java(*start_java(ros_protos(work / "protos", JAVA_TYPES, cast_test_msgs()), work))
        return {"classes": str(built.classes), "classpath": built.classpath}

    made = once_per_run(tmp_path_factory, "ros-java", make)
    return JavaBuild(Path(made["classes"]), made["classpath"])
