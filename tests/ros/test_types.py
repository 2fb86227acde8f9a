"""Every ROS message type is an entry type with no build step: introspection, conversion, .proto generation
(docs/ros.md, "Entry types").

Real ROS: rclpy's and genpy's message classes and serialisers, in their own
interpreters (tests/ros/ros_env.py); the protobuf side is checked here with
protoc.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2

from cast.core.schema_compare import first_difference
from tests.conftest import run_to_end
from tests.ros.ros_env import HELPERS, ros1_python, ros2_python

PACKAGES = ["std_msgs", "geometry_msgs", "sensor_msgs"]
# A few types each package must have been checked with: the runs below cannot pass by checking nothing.
EXPECTED = {
    2: ["std_msgs/msg/Float64MultiArray", "std_msgs/msg/String", "geometry_msgs/msg/PoseStamped",
        "geometry_msgs/msg/PoseWithCovarianceStamped", "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo",
        "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/BatteryState", "std_msgs/msg/Byte", "std_msgs/msg/Char"],
    1: ["std_msgs/Float64MultiArray", "std_msgs/String", "std_msgs/Time", "std_msgs/Duration",
        "geometry_msgs/PoseStamped", "sensor_msgs/Image", "sensor_msgs/CameraInfo", "sensor_msgs/PointCloud2"],
}


def _round_trips(python: Path, ros: int) -> dict[str, dict[str, str | None]]:
    done = run_to_end([str(python), str(HELPERS / "roundtrip.py"), str(ros), *PACKAGES],
                      f"the ROS {ros} round trips", 120)
    assert done.returncode == 0, done.stderr
    result: dict[str, dict[str, str | None]] = json.loads(done.stdout)
    return result


@pytest.mark.parametrize("ros", [2, 1])
def test_every_standard_type_survives_a_round_trip_through_ros_with_edge_values(ros: int) -> None:
    result = _round_trips(ros2_python() if ros == 2 else ros1_python(), ros)
    types = result["types"]
    assert set(EXPECTED[ros]) <= set(types)
    per_package = {p: sum(1 for t in types if t.startswith(p + "/")) for p in PACKAGES}
    assert per_package["std_msgs"] >= 29 and per_package["geometry_msgs"] >= 25 and per_package["sensor_msgs"] >= 25
    failed = {name: error for name, error in types.items() if error}
    assert not failed, "\n\n".join(f"{name}:\n{error}" for name, error in failed.items())

    # A value ROS cannot hold is refused, naming the field and the limit.
    misfits = result["misfits"]
    assert misfits["uint8 over 255"] == "field is_bigendian: 256 does not fit a ROS uint8 (0 to 255)"
    assert misfits["int8 under -128"] == "field data: -129 does not fit a ROS int8 (-128 to 127)"
    k = "k" if ros == 2 else "K"
    assert misfits["fixed array too short"] == f"field {k}: 8 values for a fixed array of exactly 9 (float64[9])"
    assert misfits["nested fixed array"] == \
        "field pose.covariance: 35 values for a fixed array of exactly 36 (float64[36])"
    assert misfits["int16 in an array"] == "field data[1]: 40000 does not fit a ROS int16 (-32768 to 32767)"


def _generate(python: Path, ros: int, out: Path, *types: str) -> subprocess.CompletedProcess[str]:
    return run_to_end([str(python), "-m", "cast.cli", "ros-types", "--ros", str(ros), *types, "-o", str(out / "protos"),
                       "--descriptor-set", str(out / "runtime.binpb")], "cast ros-types", 60)


@pytest.mark.parametrize("ros", [2, 1])
def test_the_generated_proto_files_compile_to_the_descriptors_the_bridge_registers(ros: int, tmp_path: Path) -> None:
    done = _generate(ros2_python() if ros == 2 else ros1_python(), ros, tmp_path, *PACKAGES)
    assert done.returncode == 0, done.stderr
    protos = sorted(p.relative_to(tmp_path / "protos").as_posix() for p in (tmp_path / "protos").rglob("*.proto"))
    compiled = tmp_path / "compiled.binpb"
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{tmp_path / 'protos'}",
                    f"--descriptor_set_out={compiled}", *protos], check=True)
    by_protoc = {f.name: f for f in descriptor_pb2.FileDescriptorSet.FromString(compiled.read_bytes()).file}
    at_runtime = {f.name: f for f in descriptor_pb2.FileDescriptorSet.FromString(
        (tmp_path / "runtime.binpb").read_bytes()).file}
    assert set(by_protoc) == set(at_runtime) == set(protos)
    differences = {name: first_difference(at_runtime[name], by_protoc[name]) for name in protos}
    assert not any(differences.values()), {k: v for k, v in differences.items() if v}
    # What the files say, on one type of each kind of field.
    prefix = "ros2/sensor_msgs/msg" if ros == 2 else "ros1/sensor_msgs/msg"
    image = (tmp_path / "protos" / prefix / "image.proto").read_text()
    info = (tmp_path / "protos" / prefix / "camera_info.proto").read_text()
    battery = (tmp_path / "protos" / prefix / "battery_state.proto").read_text()
    assert "  bytes data = 7;" in image and f"package ros{ros}.sensor_msgs.msg;" in image
    assert "(exactly 9 values)" in info and "repeated double" in info
    assert "//   uint8 POWER_SUPPLY_STATUS_FULL = 4" in battery
    header = (tmp_path / "protos" / f"ros{ros}" / "std_msgs" / "msg" / "header.proto").read_text()
    if ros == 2:
        assert "  .ros2.builtin_interfaces.msg.Time stamp = 1;" in header
    else:
        assert "  uint32 seq = 1;" in header and "  .ros1.builtin.Time stamp = 2;" in header


def test_a_wrong_type_name_is_refused_with_what_to_write(tmp_path: Path) -> None:
    done = _generate(ros2_python(), 2, tmp_path, "sensor_msgs/Image")
    assert done.returncode == 2
    assert "'sensor_msgs/Image' is not a ROS 2 message type name: write it as package/msg/Name" in done.stderr
    done = _generate(ros2_python(), 2, tmp_path, "sensor_msgs/msg/Imag")
    assert done.returncode == 2 and "package sensor_msgs has no message Imag (it has: BatteryState," in done.stderr
    done = _generate(ros1_python(), 1, tmp_path, "no_such_msgs/Thing")
    assert done.returncode == 2 and "ROS 1 type no_such_msgs/Thing: no Python package 'no_such_msgs'" in done.stderr
    assert not (tmp_path / "protos").exists()
