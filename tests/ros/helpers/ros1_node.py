"""A plain rospy node for the bridge's tests: publishes numbered geometry_msgs/PoseStamped messages.

    ros1_node.py publish TOPIC RATE COUNT [--start N]

Waits until a subscriber is connected (rospy drops what is published
before), then publishes message i with frame_id "frame-<i>" and x = i,
printing "published <i> <stamp ns>" for each and "done" at the end.
"""

from __future__ import annotations

import sys
import time

import rospy
from geometry_msgs.msg import PoseStamped


def main() -> int:
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
