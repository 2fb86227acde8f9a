"""Faults around the ROS bridge: a ROS publisher that dies and comes back, a ROS 1 master that restarts,
a CAST server that restarts. The bridge keeps (or makes again) its mappings without a restart of its own,
and nothing it took from ROS is lost.

Each test prints what was lost and how long recovery took, and records it in
build/ros-fault-figures.json (docs/ros.md, "Faults" has a run's table). The
times are measurements, not assertions: the tests assert only what was lost.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

import cast
from tests.conftest import ROOT, ServerHandle, serve, stop_process, wait_for
from tests.ros.bridge_support import start_bridge
from tests.ros.ros_env import helper, ros1_python, ros2_python, roscore
from tests.ros.test_ros1_bridge import image_publisher, picture
from tests.ros.test_ros2_bridge import published

FIGURES = ROOT / "build" / "ros-fault-figures.json"
POSE_TYPE = {2: "ros2.geometry_msgs.msg.PoseStamped", 1: "ros1.geometry_msgs.msg.PoseStamped"}


def record(name: str, figures: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    """Print one fault's figures and keep them in build/ros-fault-figures.json."""
    FIGURES.parent.mkdir(parents=True, exist_ok=True)
    try:
        data = json.loads(FIGURES.read_text())
    except (OSError, ValueError):
        data = {}
    data[name] = figures
    FIGURES.write_text(json.dumps(data, indent=2, sort_keys=True))
    with capsys.disabled():
        print(f"\nFAULT {name}: " + ", ".join(f"{k} {v}" for k, v in figures.items()))


def frames_in_wm(component: cast.Component, ros: int) -> dict[int, int]:
    """Frame number -> the entry's write time (ns, server clock) of every pose entry in the motor WM."""
    if ros == 2:
        from ros2.geometry_msgs.msg.pose_stamped_pb2 import PoseStamped
    else:
        from ros1.geometry_msgs.msg.pose_stamped_pb2 import PoseStamped  # type: ignore[no-redef]
    return {int(e.value.header.frame_id.removeprefix("frame-")): e.modified_ns
            for e in component.get_all(PoseStamped, subarchitecture="motor")}


def bridge_status(component: cast.Component, sa: str = "motor") -> Any:
    from cast.v1 import bridge_pb2

    try:
        return component.get("bridge.status", bridge_pb2.BridgeStatus, subarchitecture=sa)
    except cast.CastError:
        return None


def pose_mapping(ros: int, keep: int = 1000) -> dict[str, Any]:
    topic_type = "geometry_msgs/msg/PoseStamped" if ros == 2 else "geometry_msgs/PoseStamped"
    return {"topic": "/robot/pose", "type": topic_type, "subarchitecture": "motor", "store": "each", "id": "pose",
            "keep": keep, "qos": {"depth": 100}}


def first_after(frames: dict[int, int], numbers: range) -> int:
    return min(frames[i] for i in numbers if i in frames)


def test_a_ros2_publisher_that_dies_and_comes_back(
        ros_server: ServerHandle, ros2: dict[str, str], ros2_types: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    python = ros2_python()
    bridge = start_bridge(ros_server, "bridge", "motor", {"version": 2, "status_period": 0.5,
                                                          "to_wm": [pose_mapping(2)]}, ros2, tmp_path / "bridge.log")
    watcher = ros_server.connect("watcher", "motor")
    procs = []
    try:
        wait_for(lambda: bridge_status(watcher), 60, "the bridge's first status")
        first = helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "60", env=ros2,
                       log=tmp_path / "first.log")
        procs.append(first)
        wait_for(lambda: len(published(tmp_path / "first.log")) >= 20, 60, "20 poses published")
        os.killpg(first.pid, signal.SIGKILL)  # the driver dies mid-stream
        first.wait(10)
        died = time.time_ns()
        again = helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "30", "--start", "100",
                       env=ros2, log=tmp_path / "again.log")
        procs.append(again)
        assert again.wait(60) == 0, (tmp_path / "again.log").read_text()
        sent_first, sent_again = published(tmp_path / "first.log"), published(tmp_path / "again.log")
        frames = wait_for(lambda: (lambda f: f if all(i in f for i in sent_again) else None)(
            frames_in_wm(watcher, 2)), 30, "every pose of the new publisher")
        status = wait_for(lambda: (lambda s: s if s and s.mappings[0].delivered == len(frames) else None)(
            bridge_status(watcher)), 30, "the status to count them")
        m = status.mappings[0]
        # Nothing the bridge took from ROS is lost: every message it received is an entry.
        assert (m.received, m.dropped, m.errors, m.pending) == (len(frames), 0, 0, 0)
        assert set(sent_again) <= set(frames)
        record("ros2 publisher killed and started again", {
            "killed publisher: poses sent": len(sent_first),
            "killed publisher: poses in the WM": sum(1 for i in sent_first if i in frames),
            "its successor: poses sent": len(sent_again),
            "its successor: poses in the WM": sum(1 for i in sent_again if i in frames),
            "received by the bridge but not in the WM": m.received - len(frames),
            "recovery s (publisher killed -> its successor's first pose in the WM)":
                round((first_after(frames, range(100, 130)) - died) / 1e9, 3),
        }, capsys)
    finally:
        for p in procs:
            stop_process(p, 5)
        stop_process(bridge, 10)
        watcher._cast_close()


def test_a_ros1_master_that_restarts(
        ros_server: ServerHandle, ros1_types: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    python = ros1_python()
    picture(tmp_path / "table.png")
    with roscore(tmp_path / "ros-home") as core:
        settings = {"version": 1, "status_period": 0.3, "to_wm": [
            pose_mapping(1),
            {"topic": "/cam/image_raw", "type": "sensor_msgs/Image", "subarchitecture": "vision", "id": "camera"}],
            "to_ros": [{"watch": {"subarchitecture": "motor", "id": "answer"}, "topic": "/cast/answer",
                        "type": "std_msgs/String"}]}
        bridge = start_bridge(ros_server, "bridge", "motor", settings, core.env(), tmp_path / "bridge.log")
        watcher = ros_server.connect("watcher", "motor")
        procs: list[subprocess.Popen[str]] = []
        try:
            wait_for(lambda: bridge_status(watcher), 60, "the bridge's first status")
            procs.append(image_publisher(core, tmp_path / "table.png", tmp_path / "camera.log"))
            before = helper(python, "ros1_node.py", "publish", "/robot/pose", "30", "30", env=core.env(),
                            log=tmp_path / "before.log")
            procs.append(before)
            assert before.wait(60) == 0, (tmp_path / "before.log").read_text()
            images_before = wait_for(lambda: (lambda s: s.mappings[1].delivered if s and s.mappings[1].delivered
                                              else None)(bridge_status(watcher)), 30, "images")
            core.stop()  # the master goes away; nodes already connected keep talking
            down = time.monotonic()
            time.sleep(1.0)
            images_while_down = bridge_status(watcher).mappings[1].delivered - images_before
            core.start()  # a new master on the same port, knowing nothing of the old registrations
            up, up_ns = time.monotonic(), time.time_ns()
            wait_for(lambda: bridge_status(watcher).reconnections >= 1, 30, "the bridge to register again")
            registered = time.monotonic()
            after = helper(python, "ros1_node.py", "publish", "/robot/pose", "30", "30", "--start", "100",
                           env=core.env(), log=tmp_path / "after.log")
            procs.append(after)
            assert after.wait(60) == 0, (tmp_path / "after.log").read_text()  # it found the bridge: registered
            sent_before, sent_after = published(tmp_path / "before.log"), published(tmp_path / "after.log")
            frames = wait_for(lambda: (lambda f: f if all(i in f for i in [*sent_before, *sent_after]) else None)(
                frames_in_wm(watcher, 1)), 30, "every pose")
            status = bridge_status(watcher)
            m = status.mappings[0]
            assert (m.received, m.dropped, m.errors) == (len(frames), 0, 0)

            # The bridge's publisher is registered again too: a rostopic started now finds it.
            from ros1.std_msgs.msg.string_pb2 import String

            echo = subprocess.Popen(["rostopic", "echo", "-n", "1", "/cast/answer"], env=core.env(),
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            procs.append(echo)
            watcher.add("answer", String(data="after the restart"))
            deadline = time.monotonic() + 30
            while echo.poll() is None and time.monotonic() < deadline:
                time.sleep(0.3)
                watcher.overwrite("answer", String(data="after the restart"))
            out, _ = echo.communicate(timeout=10)
            assert out.splitlines()[0] == 'data: "after the restart"', out
            record("ros1 master restarted", {
                "poses sent": len(sent_before) + len(sent_after),
                "poses in the WM": len([i for i in [*sent_before, *sent_after] if i in frames]),
                "images written while the master was down": images_while_down,
                "re-registration s (master up -> bridge registered again)": round(registered - up, 3),
                "recovery s (master up -> first pose of a publisher started after it in the WM)":
                    round((first_after(frames, range(100, 130)) - up_ns) / 1e9, 3),
                "master down s": round(up - down, 3),
            }, capsys)
        finally:
            for p in procs:
                stop_process(p, 5)
            stop_process(bridge, 10)
            watcher._cast_close()


def test_a_cast_server_that_restarts(
        ros2: dict[str, str], ros2_types: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import yaml

    config = tmp_path / "system.yaml"
    config.write_text(yaml.safe_dump({"system": "ros-restart", "subarchitectures": {"motor": {}},
                                      "persistence": {"path": str(tmp_path / "wm.db"), "durability": "batch"}}))
    server = serve(config, own_session=True)
    port = server.endpoint.rsplit(":", 1)[1]
    python = ros2_python()
    settings = {"version": 2, "status_period": 0.3, "to_wm": [pose_mapping(2)],
                "to_ros": [{"watch": {"subarchitecture": "motor", "id": "command"}, "topic": "/cmd_vel",
                            "type": "geometry_msgs/msg/Twist"}]}
    bridge = start_bridge(server, "bridge", "motor", settings, ros2, tmp_path / "bridge.log")
    watcher = server.connect("watcher", "motor")
    procs = []
    try:
        wait_for(lambda: bridge_status(watcher), 60, "the bridge's first status")
        watcher._cast_close()
        poses = helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "120", env=ros2,
                       log=tmp_path / "poses.log")
        procs.append(poses)
        wait_for(lambda: len(published(tmp_path / "poses.log")) >= 30, 60, "30 poses published")
        server.process.kill()  # the server dies, mid-stream
        server.process.wait(10)
        down_ns = time.time_ns()
        time.sleep(1.0)
        server = serve(config, listen=f"127.0.0.1:{port}", own_session=True)
        up_ns = time.time_ns()
        assert poses.wait(60) == 0, (tmp_path / "poses.log").read_text()
        sent = published(tmp_path / "poses.log")
        watcher = server.connect("watcher", "motor")
        frames = wait_for(lambda: (lambda f: f if all(i in f for i in sent) else None)(frames_in_wm(watcher, 2)),
                          60, "every pose in the WM")
        status = wait_for(lambda: (lambda s: s if s and s.mappings[0].delivered == len(sent) else None)(
            bridge_status(watcher)), 30, "the status to count every pose")
        m = status.mappings[0]
        assert (m.received, m.dropped, m.errors, m.pending) == (len(sent), 0, 0, 0)
        during = [i for i, ns in sent.items() if down_ns <= ns < up_ns]

        # Entries still reach ROS through the watch the bridge made again.
        from ros2.geometry_msgs.msg.twist_pb2 import Twist

        echo = helper(python, "ros2_node.py", "echo", "/cmd_vel", "geometry_msgs/msg/Twist", "1", env=ros2,
                      log=tmp_path / "echo.log")
        procs.append(echo)
        wait_for(lambda: "subscribed" in (tmp_path / "echo.log").read_text(), 30, "the echo node")
        command = Twist()
        command.linear.x = 0.25
        watcher.add("command", command)
        deadline = time.monotonic() + 30
        while echo.poll() is None and time.monotonic() < deadline:
            time.sleep(0.3)
            watcher.overwrite("command", command)
        assert echo.wait(10) == 0 and '"x": 0.25' in (tmp_path / "echo.log").read_text()
        after = sorted(ns for ns in frames.values() if ns >= up_ns)
        record("cast server killed and restarted", {
            "poses sent": len(sent), "poses in the WM": sum(1 for i in sent if i in frames),
            "sent while the server was down": len(during),
            "recovery s (server up -> first write acknowledged)": round((after[0] - up_ns) / 1e9, 3),
            "backlog s (server up -> the last pose sent while down written)":
                round((max(frames[i] for i in during) - up_ns) / 1e9, 3) if during else 0.0,
            "server down s": round((up_ns - down_ns) / 1e9, 3),
        }, capsys)
    finally:
        for p in procs:
            stop_process(p, 5)
        stop_process(bridge, 10)
        watcher._cast_close()
        server.stop()
