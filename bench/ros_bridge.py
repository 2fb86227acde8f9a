"""M10: ROS publisher -> WM watcher through the ROS 2 bridge, beside ROS -> ROS in the same run.

For each size (1 KiB and 1 MiB, sensor_msgs/msg/Image mono8) at 30 Hz: first
the peer, an rclpy publisher to an rclpy subscriber (ROS -> ROS); then the same
publisher to the ROS bridge (cast.bridges.ros, as `cast run` starts it: store
latest into one entry), and a CAST watcher of that entry in a process of its
own (ROS -> WM). Latency is from the frame's header stamp (taken just before
publish) to the subscriber's callback or the watcher's. At the end the
bridge's own status entry gives what the bridge saw: stamp -> write
acknowledged (p50/p99) and the frames it replaced by a newer one before
writing them (``store: latest``: counted and shown by the bridge, not lost);
lost is what never arrived and was not reported so. The floor is a bare grpcio
unary echo of the same size spaced as the frames (bench/floors.py), the
round trip the bridge's write cannot beat. Every ROS process runs with
.venv-ros2's rclpy (`make ros-deps`), confined to loopback
(configs/ros/fastdds-localhost.xml, a domain of this run).
"""

from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cast
from bench.cast_cases import Server
from bench.floors import EchoFloor
from bench.harness import ROOT, summary_us
from cast.v1 import bridge_pb2

__all__ = ["HZ", "SIZES", "run"]

HZ = 30
SIZES = {"1 KiB": 1 << 10, "1 MiB": 1 << 20}
ROS2_PYTHON = Path(os.environ.get("CAST_ROS2_PYTHON", ROOT / ".venv-ros2" / "bin" / "python"))
TIMEOUT_S = 120


def ros_env(work: Path) -> dict[str, str]:
    """ROS 2 on loopback only, in a domain of this run."""
    (work / "ros-logs").mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + (os.getpid() + 100) % 200), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               FASTDDS_DEFAULT_PROFILES_FILE=str(ROOT / "configs" / "ros" / "fastdds-localhost.xml"),
               RMW_IMPLEMENTATION="rmw_fastrtps_cpp", ROS_LOG_DIR=str(work / "ros-logs"), PYTHONUNBUFFERED="1")
    env.pop("PYTHONPATH", None)
    return env


class _Node:
    """A bench.ros_nodes process; its lines are read on a thread."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.mode = args[0]
        self.proc = subprocess.Popen([str(ROS2_PYTHON), "-m", "bench.ros_nodes", *args], cwd=ROOT, env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip())
            if line.strip() in ("ready", "matched"):
                self.ready.set()

    def result(self, key: str) -> dict[int, int]:
        """The JSON line it printed at its end."""
        self.proc.wait(TIMEOUT_S)
        self._reader.join(10)
        for line in reversed(self.lines):
            if line.startswith("{"):
                return {int(k): int(v) for k, v in json.loads(line)[key].items()}
        raise RuntimeError(f"bench.ros_nodes {self.mode} printed no result:\n" + "\n".join(self.lines[-20:]))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


STATUS_PERIOD_S = 0.5  # the bridge's status entry, read once the last frame is in


def _figures(sent: dict[int, int], latency: dict[int, int], replaced: int = 0) -> dict[str, Any]:
    measured = [latency[i] / 1e3 for i in sent if i in latency]
    missing = sum(1 for i in sent if i not in latency)
    return {**summary_us(measured), "sent": len(sent), "received": len(measured), "replaced": replaced,
            "lost": max(0, missing - replaced)}


def _bridge_status(server: Server) -> bridge_pb2.BridgeMapping:
    """The bridge's one mapping as its latest status entry tells it (after a status period more)."""
    reader = server.component("m10-status", "robot")
    try:
        deadline = time.monotonic() + 10
        while True:
            time.sleep(STATUS_PERIOD_S * 2)
            status: bridge_pb2.BridgeStatus | None = None
            try:
                status = reader.get("bridge.status", bridge_pb2.BridgeStatus)
            except cast.NotFoundError:
                pass
            if status is not None and status.mappings:
                mapping: bridge_pb2.BridgeMapping = status.mappings[0]
                return mapping
            if time.monotonic() > deadline:
                raise RuntimeError("the bridge wrote no status entry")
    finally:
        reader._cast_close()


def _ros_to_ros(size: int, count: int, env: dict[str, str]) -> dict[str, Any]:
    sub = _Node(["subscribe", "/m10/peer", str(count)], env)
    pub: _Node | None = None
    try:
        if not sub.ready.wait(60):
            raise RuntimeError("the rclpy subscriber did not start")
        pub = _Node(["publish", "/m10/peer", str(size), str(HZ), str(count)], env)
        sent = pub.result("sent")
        return _figures(sent, sub.result("latency_ns"))
    finally:
        for node in (pub, sub):
            if node is not None:
                node.stop()


def _ros_to_wm(size: int, count: int, env: dict[str, str], work: Path) -> dict[str, Any]:
    server = Server(work, ["robot"])
    settings = {"version": 2, "node": "m10_bridge", "status_period": STATUS_PERIOD_S, "to_wm": [
        {"topic": "/m10/camera", "type": "sensor_msgs/msg/Image", "id": "frame", "qos": {"depth": 10}}]}
    bridge = subprocess.Popen([str(ROS2_PYTHON), "-m", "cast.run", "cast.bridges.ros.ros2:Ros2Bridge"], cwd=ROOT,
                              env={**env, **server.env("bridge", "robot"), "CAST_ROS_BRIDGE": json.dumps(settings)},
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    watcher = _Node(["wm-watch", "frame", str(count)], {**env, **server.env("watcher", "robot")})
    pub: _Node | None = None
    try:
        if not watcher.ready.wait(60):
            raise RuntimeError("the WM watcher did not start")
        pub = _Node(["publish", "/m10/camera", str(size), str(HZ), str(count)], env)
        sent = pub.result("sent")
        latency = watcher.result("latency_ns")
        mapping = _bridge_status(server)
        return {**_figures(sent, latency, replaced=mapping.dropped),
                "bridge_received": mapping.received, "bridge_delivered": mapping.delivered,
                "ack_p50_us": round(mapping.latency_p50_seconds * 1e6, 1),
                "ack_p99_us": round(mapping.latency_p99_seconds * 1e6, 1)}
    finally:
        for node in (pub, watcher):
            if node is not None:
                node.stop()
        bridge.terminate()
        try:
            bridge.wait(15)
        except subprocess.TimeoutExpired:
            bridge.kill()
            bridge.wait()
        server.stop()


def run(work: Path, count: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Both paths for each size: {"1 KiB": {"ros_ros": {...}, "ros_wm": {...}}, ...}, or {"error": why}."""
    if not os.access(ROS2_PYTHON, os.X_OK):
        return {"error": f"no ROS 2 interpreter at {ROS2_PYTHON}: `make ros-deps` installs it"}
    env = ros_env(work)
    out: dict[str, Any] = {"count": count, "hz": HZ}
    echo = EchoFloor()
    try:
        for label, size in SIZES.items():
            log(f"M10 {label} at {HZ} Hz: rclpy -> rclpy ({count} frames)")
            peer = _ros_to_ros(size, count, env)
            log(f"M10 {label} at {HZ} Hz: rclpy -> ROS bridge -> WM watcher ({count} frames)")
            bridged = _ros_to_wm(size, count, env, work / f"m10-{size}")
            log(f"M10 {label} floor: bare gRPC unary echo at {HZ} Hz")
            floor = echo.big_echo(max(20, count // 2), size, gap_s=1 / HZ)
            out[label] = {"ros_ros": peer, "ros_wm": bridged, "floor": floor}
    except (RuntimeError, OSError, subprocess.TimeoutExpired, cast.CastError) as exc:
        out["error"] = str(exc)
    finally:
        echo.close()
    return out
