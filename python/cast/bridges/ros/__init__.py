"""The ROS bridge: ROS 2 (rclpy) and ROS 1 (rospy) topics to and from working memories (docs/ros.md).

What lives here, by job:

- ``model``: a ROS message type as both ROS generations describe it (fields,
  arrays and their bounds, nested types, constants), and the naming scheme that
  turns it into a protobuf entry type (``ros2.sensor_msgs.msg.Image``).
- ``ros2_types``, ``ros1_types``: that model read at run time from the ROS
  client library's own message classes (no build step for any message type).
- ``descriptors``: protobuf descriptors and message classes built from the
  model at run time; ``protofile``: the same types as ``.proto`` text for the
  C++, Java and Python builds (``cast ros-types``).
- ``convert``: field-by-field conversion both ways, with range checks.
- ``bridge``, ``ros2``, ``ros1``: the component (mappings, buffering, status)
  and its two ROS sides.

Nothing here imports rclpy or rospy at module level: each ROS side is
imported only by the interpreter that runs it.
"""
