"""The ROS 2 bridge against real rclpy nodes: topics into WMs, entries out to topics, every field checked.

The bridge runs as `cast run` starts it (its interpreter, the runner, CAST_ROS_BRIDGE);
the ROS 2 nodes are plain rclpy processes (tests/ros/helpers/ros2_node.py) on
loopback; the watcher here decodes with the types `cast ros-types` generated. A team's
own message package is one the test builds (tests/ros/helpers/build_ros2_msgs.py).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

import cast
from tests.conftest import ServerHandle, stop_process, wait_for
from tests.ros.bridge_support import cast_test_msgs, generate_types, start_bridge
from tests.ros.builds import JavaBuild, printed, wait_ready
from tests.ros.ros_env import helper, ros2_python

BRIDGE_SETTINGS: dict[str, Any] = {
    "version": 2,
    "node": "cast_bridge",
    "namespace": "/test",
    "status_period": 0.5,
    "to_wm": [
        {"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image", "subarchitecture": "vision",
         # Depth for every frame the test sends: a slow bridge (a loaded machine) must not lose frames in
         # DDS's history before it counts them, since the test checks that it accounts for each one.
         "store": "latest", "id": "camera", "qos": {"depth": 50}},
        {"topic": "/robot/pose", "type": "geometry_msgs/msg/PoseStamped", "subarchitecture": "motor",
         "store": "each", "id": "pose", "keep": 25},
    ],
    "to_ros": [
        {"watch": {"subarchitecture": "motor", "id": "command"}, "topic": "/cmd_vel",
         "type": "geometry_msgs/msg/Twist"},
    ],
}


def published(log: Path) -> dict[int, int]:
    """Message number -> header stamp (ns) from a publisher helper's log."""
    out = {}
    for line in log.read_text().splitlines():
        if line.startswith("published "):
            _, i, stamp = line.split()
            out[int(i)] = int(stamp)
    return out


def status_of(watcher: cast.Component, bridge: str, sa: str = "motor") -> Any:
    from cast.v1 import bridge_pb2

    try:
        return watcher.get(f"{bridge}.status", bridge_pb2.BridgeStatus, subarchitecture=sa)
    except cast.NotFoundError:
        return None


def test_topics_reach_the_wm_with_every_field_and_entries_reach_ros(
        ros_server: ServerHandle, ros2: dict[str, str], ros2_types: Path, tmp_path: Path) -> None:
    from ros2.geometry_msgs.msg.pose_stamped_pb2 import PoseStamped
    from ros2.geometry_msgs.msg.twist_pb2 import Twist
    from ros2.sensor_msgs.msg.image_pb2 import Image

    python = ros2_python()
    bridge = start_bridge(ros_server, "bridge", "motor", BRIDGE_SETTINGS, ros2, tmp_path / "bridge.log")
    watcher = ros_server.connect("watcher", "vision")
    images: list[Image] = []
    poses: dict[str, PoseStamped] = {}
    mutex = threading.Lock()

    def on_image(change: cast.WorkingMemoryChange) -> None:
        with mutex:
            images.append(change.entry(Image).value)

    def on_pose(change: cast.WorkingMemoryChange) -> None:
        with mutex:
            poses[change.id] = change.entry(PoseStamped).value

    watcher.on_change(cast.ChangeFilter(type="ros2.sensor_msgs.msg.Image", subarchitecture="vision",
                                        include_entry=True), on_image)
    watcher.on_change(cast.ChangeFilter(frozenset({cast.Operation.ADD}), type="ros2.geometry_msgs.msg.PoseStamped",
                                        subarchitecture="motor", include_entry=True), on_pose)
    procs = []
    try:
        wait_for(lambda: status_of(watcher, "bridge"), 60, "the bridge's first status entry")
        procs.append(helper(python, "ros2_node.py", "publish", "/camera/image_raw", "image", "30", "45",
                            env=ros2, log=tmp_path / "images.log"))
        procs.append(helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "40",
                            env=ros2, log=tmp_path / "poses.log"))
        for p in procs:
            assert p.wait(60) == 0, (tmp_path / "images.log").read_text() + (tmp_path / "poses.log").read_text()
        sent_images, sent_poses = published(tmp_path / "images.log"), published(tmp_path / "poses.log")
        assert len(sent_images) == 45 and len(sent_poses) == 40

        # The latest image is in the WM, every field as the driver sent it.
        wait_for(lambda: images and images[-1].header.frame_id == "frame-44", 30, "the last image")
        last = images[-1]
        assert (last.height, last.width, last.encoding, last.is_bigendian, last.step) == (480, 640, "rgb8", 0, 1920)
        assert last.data == bytes((x + 44) % 256 for x in range(640 * 3)) * 480
        assert last.header.stamp.sec * 1_000_000_000 + last.header.stamp.nanosec == sent_images[44]
        entry = watcher.get_entry("camera", Image, subarchitecture="vision")
        assert entry.author == "bridge" and entry.value == last

        # Poses: one entry each (store: each), none lost, the newest 25 kept.
        wait_for(lambda: len(poses) == 40, 30, "40 pose entries")
        by_frame = {p.header.frame_id: (entry_id, p) for entry_id, p in poses.items()}
        assert set(by_frame) == {f"frame-{i}" for i in range(40)}
        for i in range(40):
            entry_id, p = by_frame[f"frame-{i}"]
            assert entry_id.startswith("pose/")
            assert (p.pose.position.x, p.pose.position.y, p.pose.position.z) == (float(i), -2.5, 1e-300)
            assert (p.pose.orientation.z, p.pose.orientation.w) == (0.6, 0.8)
            assert p.header.stamp.sec * 1_000_000_000 + p.header.stamp.nanosec == sent_poses[i]
        kept = wait_for(lambda: (lambda ids: ids if len(ids) == 25 else None)(
            sorted(e.id for e in watcher.get_all(PoseStamped, subarchitecture="motor"))), 30, "25 poses kept")
        assert kept == sorted(by_frame[f"frame-{i}"][0] for i in range(15, 40))

        # An entry written in the WM reaches an rclpy subscriber as geometry_msgs/msg/Twist.
        echo = helper(python, "ros2_node.py", "echo", "/cmd_vel", "geometry_msgs/msg/Twist", "1", env=ros2,
                      log=tmp_path / "echo.log")
        procs.append(echo)
        wait_for(lambda: "subscribed" in (tmp_path / "echo.log").read_text(), 30, "the echo node")
        command = Twist()
        command.linear.x, command.linear.y, command.angular.z = 0.5, -1e-9, float("inf")
        writer = ros_server.connect("planner", "motor")
        writer.add("command", command)
        # DDS may match the echo after the first write: the same command again until it arrives.
        for _ in range(100):
            if echo.poll() is not None:
                break
            writer.overwrite("command", command)
            time.sleep(0.3)
        assert echo.wait(30) == 0, (tmp_path / "echo.log").read_text()
        lines = (tmp_path / "echo.log").read_text().splitlines()
        got = json.loads(lines[lines.index("subscribed") + 1])
        assert got["linear"] == {"x": 0.5, "y": -1e-9, "z": 0.0}
        assert got["angular"] == {"x": 0.0, "y": 0.0, "z": float("inf")}
        writer._cast_close()

        # The status entry says what each mapping did.
        def settled() -> Any:
            s = status_of(watcher, "bridge")
            return s if s is not None and s.mappings[1].delivered == 40 and s.mappings[2].delivered >= 1 else None

        status = wait_for(settled, 30, "the status to count every message")
        image_map, pose_map, twist_map = status.mappings
        assert (image_map.direction, image_map.topic, image_map.entry_type) == (
            "to_wm", "/camera/image_raw", "ros2.sensor_msgs.msg.Image")
        assert image_map.received == 45 and image_map.delivered + image_map.dropped == 45 and image_map.errors == 0
        assert pose_map.received == 40 and pose_map.dropped == 0 and pose_map.errors == 0
        assert 0 < pose_map.latency_p50_seconds <= pose_map.latency_max_seconds < 5  # a bound, not a benchmark
        assert twist_map.direction == "to_ros" and twist_map.errors == 0
        assert status.node == "/test/cast_bridge" and "domain" in status.middleware

        # A bridge started again counts the entries its predecessor left: keep still bounds them.
        stop_process(bridge, 10)
        bridge = start_bridge(ros_server, "bridge", "motor", BRIDGE_SETTINGS, ros2, tmp_path / "bridge-2.log")
        wait_for(lambda: (lambda s: s and s.mappings[1].received == 0)(status_of(watcher, "bridge")), 60,
                 "the second bridge's first status")
        more = helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "5", "--start", "200",
                      env=ros2, log=tmp_path / "more.log")
        procs.append(more)
        assert more.wait(60) == 0, (tmp_path / "more.log").read_text()
        wait_for(lambda: len(poses) == 45, 30, "5 more pose entries")
        kept = wait_for(lambda: (lambda es: es if len(es) == 25 and "frame-204" in {e.value.header.frame_id for e in es}
                                 else None)(watcher.get_all(PoseStamped, subarchitecture="motor")), 30, "25 kept")
        frames = sorted(int(e.value.header.frame_id.removeprefix("frame-")) for e in kept)
        assert frames == [*range(20, 40), *range(200, 205)]
    finally:
        for p in procs:
            stop_process(p, 5)  # type: ignore[arg-type]
        stop_process(bridge, 10)
        watcher._cast_close()


def fnv1a(data: bytes) -> str:
    h = 0xCBF29CE484222325
    for b in data:
        h = ((h ^ b) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return f"{h:x}"


def sent_pose(i: int, stamp_ns: int) -> dict[str, Any]:
    """Pose i as tests/ros/helpers/ros2_node.py publishes it, rosidl's field names (as the watchers print it)."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return {"header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": f"frame-{i}"},
            "pose": {"position": {"x": float(i), "y": -2.5, "z": 1e-300},
                     "orientation": {"x": 0.0, "y": 0.0, "z": 0.6, "w": 0.8}}}


def sent_reading(i: int, stamp_ns: int) -> dict[str, Any]:
    """cast_test_msgs/msg/Reading i as tests/ros/helpers/ros2_node.py publishes it (bytes as hex)."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return {"header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": f"frame-{i}"}, "level": 2,
            "value": -0.125, "triple": [-32768, 0, 32767], "label": f"tank {i}: ünïcødé",
            "points": [{"x": 1.0, "y": 2.0, "z": 3.0}, {"x": -1.0, "y": float("inf"), "z": -0.0}],
            "gains": [0.5, -1.5], "blob": (bytes([i]) + bytes(range(256))).hex(), "code": "ca5700ff",
            "count": -(2**63), "window": {"sec": -2, "nanosec": 500}}


# The first test of the run to use them builds the C++ and Java components (a few minutes on a busy machine).
@pytest.mark.timeout(600)
def test_cpp_and_java_components_decode_every_field_of_images_poses_and_own_messages_and_a_java_command_reaches_rclpy(
        ros_server: ServerHandle, ros2: dict[str, str], ros_java_build: JavaBuild, ros_cpp_build: Path,
        tmp_path: Path) -> None:
    # Java first: the ROS 1 bridge's tests, on the other pytest worker, build the C++ component meanwhile.
    cpp_exe, java = ros_cpp_build, ros_java_build
    python = ros2_python()
    overlay = cast_test_msgs()
    node_env = {**ros2, **{k: os.pathsep.join(p for p in (v, ros2.get(k, "")) if p) for k, v in overlay.items()}}
    settings = {"version": 2, "status_period": 0.5, "to_wm": [
        *BRIDGE_SETTINGS["to_wm"],
        {"topic": "/tank/reading", "type": "cast_test_msgs/msg/Reading", "subarchitecture": "language",
         "store": "each", "id": "tank"}], "to_ros": BRIDGE_SETTINGS["to_ros"]}
    bridge = start_bridge(ros_server, "bridge", "motor", settings, ros2, tmp_path / "bridge.log", overlay=overlay)
    counts = {"image": 1, "pose": 5, "reading": 3}
    watch = {"watch": {"ros2.sensor_msgs.msg.Image": {"sa": "vision", "count": counts["image"]},
                       "ros2.geometry_msgs.msg.PoseStamped": {"sa": "motor", "count": counts["pose"]},
                       "ros2.cast_test_msgs.msg.Reading": {"sa": "language", "count": counts["reading"]}}}
    cpp = subprocess.Popen([str(cpp_exe)], env=ros_server.env("cpp_watcher", "vision", args=watch),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, encoding="utf-8")
    jvm = subprocess.Popen(java.command(), env=ros_server.env("java_watcher", "vision", args=watch),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, encoding="utf-8")
    procs: list[subprocess.Popen[str]] = [cpp, jvm]
    try:
        for p in (cpp, jvm):
            wait_ready(p)
        watcher = ros_server.connect("watcher", "motor")
        wait_for(lambda: status_of(watcher, "bridge"), 60, "the bridge's first status entry")
        publishers = {kind: helper(python, "ros2_node.py", "publish", topic, kind, "30", str(counts[kind] * n),
                                   env=node_env, log=tmp_path / f"{kind}.log")
                      for kind, topic, n in (("image", "/camera/image_raw", 10), ("pose", "/robot/pose", 1),
                                             ("reading", "/tank/reading", 1))}
        procs.extend(publishers.values())
        for kind, p in publishers.items():
            assert p.wait(60) == 0, (tmp_path / f"{kind}.log").read_text()
        sent = {kind: published(tmp_path / f"{kind}.log") for kind in publishers}
        for p in (cpp, jvm):
            out, _ = p.communicate(timeout=60)
            assert p.returncode == 0, out
            got: dict[str, list[dict[str, Any]]] = {}
            for line in printed(out):
                got.setdefault(line.pop("type"), []).append(line)
            assert {k: len(v) for k, v in got.items()} == {
                "ros2.sensor_msgs.msg.Image": 1, "ros2.geometry_msgs.msg.PoseStamped": 5,
                "ros2.cast_test_msgs.msg.Reading": 3}, out

            # The latest image (store: latest): every field, the pixels by their hash.
            [image] = got["ros2.sensor_msgs.msg.Image"]
            i = int(image["frame_id"].removeprefix("frame-"))
            assert image == {"id": "camera", "frame_id": f"frame-{i}", "stamp_ns": sent["image"][i], "height": 480,
                             "width": 640, "encoding": "rgb8", "is_bigendian": 0, "step": 1920, "size": 921600,
                             "fnv": fnv1a(bytes((x + i) % 256 for x in range(640 * 3)) * 480)}

            # Poses and readings (store: each): one entry per message, every field as rclpy sent it.
            for type_name, kind, prefix, expected in (
                    ("ros2.geometry_msgs.msg.PoseStamped", "pose", "pose/", sent_pose),
                    ("ros2.cast_test_msgs.msg.Reading", "reading", "tank/", sent_reading)):
                entries = sorted(got[type_name], key=lambda e: e["header"]["frame_id"])
                assert all(e.pop("id").startswith(prefix) for e in entries), entries
                assert entries == [expected(i, sent[kind][i]) for i in range(counts[kind])]
            for r in got["ros2.cast_test_msgs.msg.Reading"]:
                assert math.copysign(1.0, r["points"][1]["z"]) == -1.0  # -0.0 kept

        # A Java component writes a command; an rclpy node receives it as geometry_msgs/msg/Twist.
        echo = helper(python, "ros2_node.py", "echo", "/cmd_vel", "geometry_msgs/msg/Twist", "1", env=ros2,
                      log=tmp_path / "echo.log")
        procs.append(echo)
        wait_for(lambda: "subscribed" in (tmp_path / "echo.log").read_text(), 30, "the echo node")
        commander = subprocess.Popen(java.command(), env=ros_server.env("java_commander", "motor", args={
            "mode": "command", "sa": "motor"}), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        procs.append(commander)
        assert echo.wait(60) == 0, (tmp_path / "echo.log").read_text()
        lines = (tmp_path / "echo.log").read_text().splitlines()
        got_twist = json.loads(lines[lines.index("subscribed") + 1])
        assert got_twist == {"linear": {"x": 0.75, "y": -2.0, "z": 0.0},
                             "angular": {"x": 0.0, "y": 0.0, "z": -1.5e-7}}
        watcher._cast_close()
    finally:
        for p in procs:
            stop_process(p, 5)
        stop_process(bridge, 10)


def test_a_type_this_ros_does_not_have_stops_the_bridge_before_it_starts_naming_it(
        ros_server: ServerHandle, ros2: dict[str, str], tmp_path: Path) -> None:
    settings = {"version": 2, "to_wm": [{"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Imag"}]}
    bridge = start_bridge(ros_server, "bridge", "motor", settings, ros2, tmp_path / "bridge.log")
    try:
        assert bridge.wait(60) != 0
    finally:
        stop_process(bridge, 5)
    log = (tmp_path / "bridge.log").read_text()
    assert ("ROS bridge bridge, to_wm[0] (/camera/image_raw): ROS 2 type sensor_msgs/msg/Imag: package sensor_msgs "
            "has no message Imag (it has: BatteryState, CameraInfo,") in log, log


# The first run builds the message package (rosidl generators and gcc, about 15 s; cached in build/ros2-msgs).
@pytest.mark.timeout(300)
def test_a_teams_own_ros2_message_package_is_bridged_both_ways_as_soon_as_it_is_on_the_ros_path(
        ros_server: ServerHandle, ros2: dict[str, str], tmp_path: Path) -> None:
    overlay = cast_test_msgs()
    settings = {"version": 2, "status_period": 0.3, "to_wm": [
        {"topic": "/tank/reading", "type": "cast_test_msgs/msg/Reading", "subarchitecture": "language",
         "store": "each", "id": "tank"}], "to_ros": [
        {"watch": {"subarchitecture": "language", "id": "setpoint"}, "topic": "/tank/setpoint",
         "type": "cast_test_msgs/msg/Reading"}]}

    # Not on the ROS path, or only its Python half (PYTHONPATH without LD_LIBRARY_PATH): the bridge stops
    # before it starts, naming what it cannot find. On the path, it starts (rclpy) meanwhile.
    lost = {"none": None, "python": {"PYTHONPATH": overlay["PYTHONPATH"]}}
    refused = {k: start_bridge(ros_server, f"bridge_{k}", "language", settings, ros2, tmp_path / f"bridge-{k}.log",
                               overlay=o) for k, o in lost.items()}
    bridge = start_bridge(ros_server, "bridge", "language", settings, ros2, tmp_path / "bridge.log", overlay=overlay)
    watcher = ros_server.connect("watcher", "language")
    procs: list[subprocess.Popen[str]] = [*refused.values()]
    try:
        # The team's entry types for its own components: cast ros-types on the same path, protoc for Python.
        sys.path.insert(0, str(generate_types(tmp_path / "types", 2, "cast_test_msgs/msg/Reading", overlay=overlay)))
        from ros2.cast_test_msgs.msg.reading_pb2 import Reading

        proto = (tmp_path / "types" / "protos" / "ros2" / "cast_test_msgs" / "msg" / "reading.proto").read_text()
        assert "//   uint8 LEVEL_HIGH = 2\n" in proto and "//   string UNIT = 'bar'\n" in proto, proto
        assert [f.name for f in Reading.DESCRIPTOR.fields] == [
            "header", "level", "value", "triple", "label", "points", "gains", "blob", "code", "count", "window"]

        assert [p.wait(60) != 0 for p in refused.values()] == [True, True]
        log = (tmp_path / "bridge-none.log").read_text()
        assert "to_wm[0] (/tank/reading): ROS 2 type cast_test_msgs/msg/Reading: no Python package " \
               "'cast_test_msgs' with messages" in log, log
        log = (tmp_path / "bridge-python.log").read_text()
        assert "to_wm[0] (/tank/reading): ROS 2 type cast_test_msgs/msg/Reading: the type support of package " \
               "cast_test_msgs does not load (libcast_test_msgs__rosidl_generator_py.so: cannot open shared " \
               "object file" in log, log
        assert "stop() failed" not in log + (tmp_path / "bridge-none.log").read_text(), log

        python = ros2_python()
        node_env = {**ros2, **{k: os.pathsep.join(p for p in (v, ros2.get(k, "")) if p) for k, v in overlay.items()}}
        wait_for(lambda: status_of(watcher, "bridge", "language"), 60, "the bridge's first status entry")
        publisher = helper(python, "ros2_node.py", "publish", "/tank/reading", "reading", "10", "3", env=node_env,
                           log=tmp_path / "reading.log")
        procs.append(publisher)
        assert publisher.wait(60) == 0, (tmp_path / "reading.log").read_text()
        sent = published(tmp_path / "reading.log")

        # ROS -> WM: one entry per message, every field as the rclpy node set it.
        entries = wait_for(lambda: (lambda es: es if len(es) == 3 else None)(
            watcher.get_all(Reading, subarchitecture="language")), 30, "3 readings in the WM")
        for i, r in enumerate(sorted((e.value for e in entries), key=lambda r: r.header.frame_id)):
            assert r.header.frame_id == f"frame-{i}"
            assert r.header.stamp.sec * 1_000_000_000 + r.header.stamp.nanosec == sent[i]
            assert (r.level, r.value, list(r.triple), r.label) == (2, -0.125, [-32768, 0, 32767], f"tank {i}: ünïcødé")
            assert [(p.x, p.y, p.z) for p in r.points] == [(1.0, 2.0, 3.0), (-1.0, float("inf"), 0.0)]
            assert math.copysign(1.0, r.points[1].z) == -1.0  # -0.0 kept
            assert list(r.gains) == [0.5, -1.5]
            assert r.blob == bytes([i]) + bytes(range(256)) and r.code == b"\xca\x57\x00\xff"
            assert r.count == -(2**63) and (r.window.sec, r.window.nanosec) == (-2, 500)
        assert {e.id.split("/")[0] for e in entries} == {"tank"} and {e.author for e in entries} == {"bridge"}

        # WM -> ROS: a value that does not fit is refused, naming the field and its bound; the next one goes out.
        echo = helper(python, "ros2_node.py", "echo", "/tank/setpoint", "cast_test_msgs/msg/Reading", "1",
                      env=node_env, log=tmp_path / "echo.log")
        procs.append(echo)
        wait_for(lambda: "subscribed" in (tmp_path / "echo.log").read_text(), 30, "the echo node")
        setpoint = Reading(level=1, value=float("-inf"), triple=[1, -2, 3], label="setpoint ✓ 100%", gains=[0.25],
                           blob=b"\x00\x01\xff", code=b"abcd", count=2**63 - 1)
        setpoint.header.frame_id = "cast"
        setpoint.header.stamp.sec, setpoint.header.stamp.nanosec = 5, 6
        setpoint.points.add(x=0.5, y=-0.5, z=1e-300)
        setpoint.window.sec, setpoint.window.nanosec = 3, 999_999_999
        too_long = Reading()
        too_long.CopyFrom(setpoint)
        too_long.label = "seventeen letters"
        watcher.add("setpoint", too_long)
        for _ in range(100):  # DDS may match the echo after the first write: the same again until it arrives
            if echo.poll() is not None:
                break
            watcher.overwrite("setpoint", setpoint)
            time.sleep(0.3)
        assert echo.wait(30) == 0, (tmp_path / "echo.log").read_text()
        lines = (tmp_path / "echo.log").read_text().splitlines()
        assert json.loads(lines[lines.index("subscribed") + 1]) == {
            "header": {"stamp": {"sec": 5, "nanosec": 6}, "frame_id": "cast"}, "level": 1, "value": float("-inf"),
            "triple": [1, -2, 3], "label": "setpoint ✓ 100%", "points": [{"x": 0.5, "y": -0.5, "z": 1e-300}],
            "gains": [0.25], "blob": [0, 1, 255], "code": [97, 98, 99, 100], "count": 2**63 - 1,
            "window": {"sec": 3, "nanosec": 999_999_999}}
        status = wait_for(lambda: (lambda s: s if s and s.mappings[1].delivered >= 1 else None)(
            status_of(watcher, "bridge", "language")), 30, "the status to count the setpoint")
        to_ros = status.mappings[1]
        assert to_ros.errors == 1, to_ros
        assert "field label: a string of 17 characters for string<=16 (at most 16)" in to_ros.last_error, to_ros
    finally:
        for p in procs:
            stop_process(p, 5)
        stop_process(bridge, 10)
        watcher._cast_close()
