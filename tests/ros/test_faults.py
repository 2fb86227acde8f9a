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
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
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


@dataclass
class Bridged:
    """A bridge under a fault: the component that watches the motor WM, and the ROS processes started."""

    watcher: cast.Component
    procs: list[subprocess.Popen[str]] = field(default_factory=list)

    def started(self, proc: subprocess.Popen[str]) -> subprocess.Popen[str]:
        """``proc``, stopped when the run ends."""
        self.procs.append(proc)
        return proc


@contextmanager
def bridged(server: ServerHandle, settings: dict[str, Any], env: dict[str, str], log: Path) -> Iterator[Bridged]:
    """The bridge as component `bridge` of motor and a watcher, once its first status is in the WM; at the
    end, the processes started, the bridge and the watcher (the one the test holds then) stopped."""
    bridge = start_bridge(server, "bridge", "motor", settings, env, log)
    run = Bridged(server.connect("watcher", "motor"))
    try:
        wait_for(lambda: bridge_status(run.watcher), 60, "the bridge's first status")
        yield run
    finally:
        for p in run.procs:
            stop_process(p, 5)
        stop_process(bridge, 10)
        run.watcher._cast_close()


def every_pose(watcher: cast.Component, ros: int, sent: Any, timeout: float, what: str) -> dict[int, int]:
    """frames_in_wm once it holds every frame number in ``sent``."""
    frames: dict[int, int] = wait_for(
        lambda: (lambda f: f if all(i in f for i in sent) else None)(frames_in_wm(watcher, ros)), timeout, what)
    return frames


def status_counting(watcher: cast.Component, delivered: int, what: str) -> Any:
    """The bridge's status once its pose mapping has delivered ``delivered`` messages."""
    return wait_for(lambda: (lambda s: s if s and s.mappings[0].delivered == delivered else None)(
        bridge_status(watcher)), 30, what)


def write_until_heard(watcher: cast.Component, entry_id: str, value: Any, listener: subprocess.Popen[str]) -> None:
    """Adds the entry, then overwrites it every 0.3 s until ``listener`` (a ROS echo of one message) ends,
    30 s at most: a subscriber that connects late misses the writes before it."""
    watcher.add(entry_id, value)
    deadline = time.monotonic() + 30
    while listener.poll() is None and time.monotonic() < deadline:
        time.sleep(0.3)
        watcher.overwrite(entry_id, value)


def test_a_ros2_publisher_that_dies_and_comes_back(
        ros_server: ServerHandle, ros2: dict[str, str], ros2_types: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    python = ros2_python()
    with bridged(ros_server, {"version": 2, "status_period": 0.5, "to_wm": [pose_mapping(2)]}, ros2,
                 tmp_path / "bridge.log") as run:
        first = run.started(helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "60", env=ros2,
                                   log=tmp_path / "first.log"))
        wait_for(lambda: len(published(tmp_path / "first.log")) >= 20, 60, "20 poses published")
        os.killpg(first.pid, signal.SIGKILL)  # the driver dies mid-stream
        first.wait(10)
        died = time.time_ns()
        again = run.started(helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "30", "--start",
                                   "100", env=ros2, log=tmp_path / "again.log"))
        assert again.wait(60) == 0, (tmp_path / "again.log").read_text()
        sent_first, sent_again = published(tmp_path / "first.log"), published(tmp_path / "again.log")
        frames = every_pose(run.watcher, 2, sent_again, 30, "every pose of the new publisher")
        m = status_counting(run.watcher, len(frames), "the status to count them").mappings[0]
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
        with bridged(ros_server, settings, core.env(), tmp_path / "bridge.log") as run:
            watcher = run.watcher
            run.started(image_publisher(core, tmp_path / "table.png", tmp_path / "camera.log"))
            before = run.started(helper(python, "ros1_node.py", "publish", "/robot/pose", "30", "30", env=core.env(),
                                        log=tmp_path / "before.log"))
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
            after = run.started(helper(python, "ros1_node.py", "publish", "/robot/pose", "30", "30", "--start", "100",
                                       env=core.env(), log=tmp_path / "after.log"))
            assert after.wait(60) == 0, (tmp_path / "after.log").read_text()  # it found the bridge: registered
            sent_before, sent_after = published(tmp_path / "before.log"), published(tmp_path / "after.log")
            frames = every_pose(watcher, 1, [*sent_before, *sent_after], 30, "every pose")
            status = bridge_status(watcher)
            m = status.mappings[0]
            assert (m.received, m.dropped, m.errors) == (len(frames), 0, 0)

            # The bridge's publisher is registered again too: a rostopic started now finds it.
            from ros1.std_msgs.msg.string_pb2 import String

            echo = run.started(subprocess.Popen(["rostopic", "echo", "-n", "1", "/cast/answer"], env=core.env(),
                                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
            write_until_heard(watcher, "answer", String(data="after the restart"), echo)
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
    try:
        with bridged(server, settings, ros2, tmp_path / "bridge.log") as run:
            run.watcher._cast_close()
            poses = run.started(helper(python, "ros2_node.py", "publish", "/robot/pose", "pose", "30", "120",
                                       env=ros2, log=tmp_path / "poses.log"))
            wait_for(lambda: len(published(tmp_path / "poses.log")) >= 30, 60, "30 poses published")
            server.process.kill()  # the server dies, mid-stream
            server.process.wait(10)
            down_ns = time.time_ns()
            time.sleep(1.0)
            server = serve(config, listen=f"127.0.0.1:{port}", own_session=True)
            up_ns = time.time_ns()
            assert poses.wait(60) == 0, (tmp_path / "poses.log").read_text()
            sent = published(tmp_path / "poses.log")
            run.watcher = watcher = server.connect("watcher", "motor")
            frames = every_pose(watcher, 2, sent, 60, "every pose in the WM")
            m = status_counting(watcher, len(sent), "the status to count every pose").mappings[0]
            assert (m.received, m.dropped, m.errors, m.pending) == (len(sent), 0, 0, 0)
            during = [i for i, ns in sent.items() if down_ns <= ns < up_ns]

            # Entries still reach ROS through the watch the bridge made again.
            from ros2.geometry_msgs.msg.twist_pb2 import Twist

            echo = run.started(helper(python, "ros2_node.py", "echo", "/cmd_vel", "geometry_msgs/msg/Twist", "1",
                                      env=ros2, log=tmp_path / "echo.log"))
            wait_for(lambda: "subscribed" in (tmp_path / "echo.log").read_text(), 30, "the echo node")
            command = Twist()
            command.linear.x = 0.25
            write_until_heard(watcher, "command", command, echo)
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
        server.stop()
