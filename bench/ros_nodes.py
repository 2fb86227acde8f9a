"""M10's processes on the ROS 2 side (bench/ros_bridge.py), run by the interpreter with rclpy (.venv-ros2).

    python -m bench.ros_nodes publish TOPIC BYTES HZ COUNT
    python -m bench.ros_nodes subscribe TOPIC COUNT
    python -m bench.ros_nodes wm-watch ENTRY COUNT      (a CAST component: the launch contract in its environment)

publish: sensor_msgs/msg/Image frames of BYTES bytes (mono8) at HZ, frame i's
header carrying its publish time (CLOCK_REALTIME ns) and "i" as frame_id; it
waits until one subscriber matched, prints "matched", then one JSON line
{"sent": {i: ns}} at the end. subscribe (an rclpy node) and wm-watch (a CAST
watcher of the bridged entry, decoding it with the type the bridge derives
from the same message class) print "ready", then one JSON line {"latency_ns":
{i: arrival - stamp}} once COUNT frames arrived or none came for 10 s. The
clocks are one machine's; QoS is reliable, depth 10, for every end.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

QUIET_S = 10.0


def _rclpy() -> Any:
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    return rclpy


def _qos() -> Any:
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def publish(topic: str, size: int, hz: float, count: int) -> int:
    """Publish ``count`` frames of ``size`` bytes at ``hz``."""
    rclpy = _rclpy()
    from sensor_msgs.msg import Image

    node = rclpy.create_node(f"m10_publisher_{int(time.time() * 1000) % 100000}")
    publisher = node.create_publisher(Image, topic, _qos())
    deadline = time.monotonic() + 30
    while publisher.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            print("no subscriber matched in 30 s", flush=True)
            return 1
        time.sleep(0.05)
    print("matched", flush=True)
    time.sleep(0.5)  # discovery settles both ways before the first measured frame
    width = min(size, 1024)
    payload = bytes(i % 251 for i in range(size))
    sent: dict[int, int] = {}
    period = 1.0 / hz
    start = time.monotonic()
    for i in range(count):
        frame = Image(height=size // width, width=width, encoding="mono8", step=width)
        frame.data = payload
        frame.header.frame_id = str(i)
        now = time.time_ns()
        frame.header.stamp.sec, frame.header.stamp.nanosec = divmod(now, 1_000_000_000)
        publisher.publish(frame)
        sent[i] = now
        time.sleep(max(0.0, start + (i + 1) * period - time.monotonic()))
    print(json.dumps({"sent": sent}), flush=True)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.shutdown()
    return 0


def _report(latency: dict[int, int], done: threading.Event, count: int) -> None:
    last = time.monotonic()
    seen = 0
    while not done.wait(0.1):
        if len(latency) != seen:
            seen, last = len(latency), time.monotonic()
        if len(latency) >= count or (seen and time.monotonic() - last > QUIET_S):
            break
    print(json.dumps({"latency_ns": latency}), flush=True)


def subscribe(topic: str, count: int) -> int:
    """An rclpy subscriber: arrival - stamp of each frame."""
    rclpy = _rclpy()
    from sensor_msgs.msg import Image

    node = rclpy.create_node(f"m10_subscriber_{int(time.time() * 1000) % 100000}")
    latency: dict[int, int] = {}

    def arrived(frame: Any) -> None:
        t = time.time_ns()
        latency[int(frame.header.frame_id)] = t - (frame.header.stamp.sec * 1_000_000_000 + frame.header.stamp.nanosec)

    node.create_subscription(Image, topic, arrived, _qos())
    done = threading.Event()
    reporter = threading.Thread(target=_report, args=(latency, done, count))
    reporter.start()
    print("ready", flush=True)
    while reporter.is_alive():
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.shutdown()
    return 0


def wm_watch(entry_id: str, count: int) -> int:
    """A CAST watcher of the bridged entry: arrival - header stamp of each frame written into it."""
    import cast
    from cast.bridges.ros.catalog import TypeCatalog
    from cast.client.runner import LaunchContract

    image_class = TypeCatalog(2).proto_class("sensor_msgs/msg/Image")
    c = cast.UnmanagedComponent()
    c._cast_bind(LaunchContract.from_env().connect())
    latency: dict[int, int] = {}

    def arrived(change: cast.WorkingMemoryChange) -> None:
        t = time.time_ns()
        frame: Any = change.entry(image_class).value
        latency[int(frame.header.frame_id)] = t - (frame.header.stamp.sec * 1_000_000_000 + frame.header.stamp.nanosec)

    c.on_change(cast.address_filter(entry_id, cast.Operation.ADD, cast.Operation.OVERWRITE, include_entry=True),
                arrived)
    print("ready", flush=True)
    _report(latency, threading.Event(), count)
    c._cast_close()
    return 0


def main(argv: list[str]) -> int:
    """Dispatch on the first argument."""
    mode = argv[0]
    if mode == "publish":
        return publish(argv[1], int(argv[2]), float(argv[3]), int(argv[4]))
    if mode == "subscribe":
        return subscribe(argv[1], int(argv[2]))
    if mode == "wm-watch":
        return wm_watch(argv[1], int(argv[2]))
    print(f"unknown mode {mode}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
