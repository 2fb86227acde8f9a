"""A plain rclpy node for the bridge's tests: publishes test messages, or prints what it receives.

    ros2_node.py publish TOPIC KIND RATE COUNT [--wait-subscribers N] [--start N]
    ros2_node.py echo TOPIC TYPE COUNT

publish: KIND is image (sensor_msgs/msg/Image, 640x480 rgb8, pixel values
made from the frame number), pose (geometry_msgs/msg/PoseStamped) or twist;
message i carries i in its header's frame_id ("frame-<i>") or pose/twist
values, so a reader can tell which arrived. It waits until N subscribers
match before the first message (DDS drops what is published before a reader
is discovered), prints "published <i> <stamp ns>" per message and "done".
echo: prints each message received as one JSON line (fields rosidl's way).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions


def image(i: int, stamp_ns: int) -> Any:
    from sensor_msgs.msg import Image

    msg = Image(height=480, width=640, encoding="rgb8", is_bigendian=0, step=640 * 3)
    msg.header.frame_id = f"frame-{i}"
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    row = bytes((x + i) % 256 for x in range(640 * 3))
    msg.data = row * 480
    return msg


def pose(i: int, stamp_ns: int) -> Any:
    from geometry_msgs.msg import PoseStamped

    msg = PoseStamped()
    msg.header.frame_id = f"frame-{i}"
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = float(i), -2.5, 1e-300
    msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z, msg.pose.orientation.w = 0.0, 0.0, 0.6, 0.8
    return msg


def twist(i: int, stamp_ns: int) -> Any:
    from geometry_msgs.msg import Twist

    msg = Twist()
    msg.linear.x, msg.angular.z = float(i), -0.25
    return msg


def to_plain(value: Any) -> Any:
    if hasattr(value, "get_fields_and_field_types"):
        return {name: to_plain(getattr(value, name)) for name in value.get_fields_and_field_types()}
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    if isinstance(value, bytes):
        return list(value)
    return value


def main() -> int:
    mode, topic = sys.argv[1], sys.argv[2]
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"cast_test_{mode}_{int(time.time() * 1000) % 100000}")
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    if mode == "publish":
        kind, rate, count = sys.argv[3], float(sys.argv[4]), int(sys.argv[5])
        wait = int(sys.argv[sys.argv.index("--wait-subscribers") + 1]) if "--wait-subscribers" in sys.argv else 1
        first = int(sys.argv[sys.argv.index("--start") + 1]) if "--start" in sys.argv else 0
        make = {"image": image, "pose": pose, "twist": twist}[kind]
        cls = type(make(0, 0))
        publisher = node.create_publisher(cls, topic, qos)
        deadline = time.monotonic() + 30
        while publisher.get_subscription_count() < wait:
            if time.monotonic() > deadline:
                print(f"no subscriber matched {topic} in 30 s", flush=True)
                return 1
            time.sleep(0.05)
        print("matched", flush=True)
        for i in range(first, first + count):
            stamp = time.time_ns()
            publisher.publish(make(i, stamp))
            print(f"published {i} {stamp}", flush=True)
            time.sleep(1.0 / rate)
        time.sleep(1.0)  # reliable delivery of the last ones before the node goes
        print("done", flush=True)
    else:
        type_name, count = sys.argv[3], int(sys.argv[4])
        package, _, name = type_name.split("/")
        cls = getattr(__import__(f"{package}.msg", fromlist=[name]), name)
        received: list[Any] = []
        node.create_subscription(cls, topic, lambda m: received.append(m), qos)
        print("subscribed", flush=True)
        deadline = time.monotonic() + 60
        while len(received) < count and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        for m in received:
            print(json.dumps(to_plain(m)), flush=True)
        print("done", flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
