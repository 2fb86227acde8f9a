"""A plain rospy node for the bridge's tests: publishes numbered geometry_msgs/PoseStamped messages.

    ros1_node.py publish TOPIC RATE COUNT [--start N]
    ros1_node.py reading TOPIC        (cast_test_msgs/Reading, the tests' own package, on PYTHONPATH)

Waits until a subscriber is connected (rospy drops what is published
before), then publishes message i with frame_id "frame-<i>" and x = i,
printing "published <i> <stamp ns>" for each and "done" at the end.
"""

from __future__ import annotations

import sys
import time

import rospy
from geometry_msgs.msg import PoseStamped


def reading(topic: str) -> int:
    """Publish one cast_test_msgs/Reading (values the test checks) at 10 Hz until stopped."""
    from cast_test_msgs.msg import Reading
    from geometry_msgs.msg import Point

    rospy.init_node("cast_test_reading", anonymous=True, disable_signals=True)
    pub = rospy.Publisher(topic, Reading, queue_size=10)
    msg = Reading(level=Reading.LEVEL_HIGH, value=-0.125, triple=[-32768, 0, 32767], label="tank 3: ünïcødé",
                  points=[Point(1.0, 2.0, 3.0), Point(-1.0, float("inf"), 0.0)])
    msg.header.frame_id = "tank"
    msg.header.stamp = rospy.Time(1700000000, 123456789)
    msg.taken = rospy.Time(1700000001, 5)
    msg.window = rospy.Duration(-2, 500)
    print("publishing", flush=True)
    while not rospy.is_shutdown():
        pub.publish(msg)
        time.sleep(0.1)
    return 0


def main() -> int:
    if sys.argv[1] == "reading":
        return reading(sys.argv[2])
    topic, rate, count = sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
    first = int(sys.argv[sys.argv.index("--start") + 1]) if "--start" in sys.argv else 0
    rospy.init_node(f"cast_test_publisher_{first}", anonymous=True, disable_signals=True)
    pub = rospy.Publisher(topic, PoseStamped, queue_size=100, tcp_nodelay=True)
    deadline = time.monotonic() + 30
    while pub.get_num_connections() < 1:
        if time.monotonic() > deadline:
            print(f"no subscriber connected to {topic} in 30 s", flush=True)
            return 1
        time.sleep(0.05)
    print("matched", flush=True)
    for i in range(first, first + count):
        msg = PoseStamped()
        msg.header.frame_id = f"frame-{i}"
        msg.header.stamp = rospy.Time.now()
        msg.pose.position.x = float(i)
        msg.pose.orientation.w = 1.0
        pub.publish(msg)
        print(f"published {i} {msg.header.stamp.to_nsec()}", flush=True)
        time.sleep(1.0 / rate)
    time.sleep(1.0)
    print("done", flush=True)
    rospy.signal_shutdown("done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
