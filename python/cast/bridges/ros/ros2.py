"""The ROS 2 side of the bridge: an rclpy node of its own name and namespace (``Ros2Bridge``).

The node has a context of its own and spins on one executor thread; rclpy
installs no signal handlers (the component's runner owns SIGINT and
SIGTERM). Discovery, the domain and the middleware are rclpy's as the
environment sets them (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``,
``RMW_IMPLEMENTATION``, ``FASTDDS_DEFAULT_PROFILES_FILE``): the bridge is a ROS 2
node like any other. DDS rediscovers publishers that die and come back by
itself, so ``poll`` has nothing to do.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import Any

from cast.bridges.ros.bridge import RosBridge, RosSide
from cast.config.ros import RosBridgeConfig, RosQos

__all__ = ["Ros2Bridge", "Ros2Side", "qos_profile"]


def qos_profile(qos: RosQos) -> Any:
    """The rclpy ``QoSProfile`` of a mapping's QoS."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE if qos.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if qos.durability == "transient_local"
        else DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_ALL if qos.history == "keep_all" else HistoryPolicy.KEEP_LAST,
        depth=qos.depth)


class Ros2Side:
    """An rclpy node, its subscriptions and publishers, spinning on a thread of its own."""

    def __init__(self, node_name: str, namespace: str) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(node_name, namespace=namespace or "/", context=self.context)
        self.node_name = self.node.get_fully_qualified_name()
        rmw = os.environ.get("RMW_IMPLEMENTATION") or "the default middleware"
        self.middleware = f"ROS 2 (rclpy, {rmw}, domain {self.context.get_domain_id()})"
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._held: list[Any] = []  # subscriptions and publishers live as long as the node
        self._thread = threading.Thread(target=self._spin, name="rclpy-executor", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def subscribe(self, topic: str, cls: Any, qos: RosQos, callback: Callable[[Any], None]) -> None:
        """A subscription whose messages go to ``callback`` on the executor thread."""
        self._held.append(self.node.create_subscription(cls, topic, callback, qos_profile(qos)))

    def advertise(self, topic: str, cls: Any, qos: RosQos) -> Callable[[Any], None]:
        """A publisher; its ``publish``."""
        publisher = self.node.create_publisher(cls, topic, qos_profile(qos))
        self._held.append(publisher)
        return publisher.publish  # type: ignore[no-any-return]

    def poll(self) -> bool:
        """Nothing to register again: DDS discovery is continuous."""
        return False

    def close(self) -> None:
        """Stop spinning, destroy the node, shut the context down."""
        self.executor.shutdown(timeout_sec=2)
        self.node.destroy_node()
        if self.context.ok():
            self._rclpy.shutdown(context=self.context)
        self._thread.join(5)


class Ros2Bridge(RosBridge):
    """The ROS bridge for ROS 2 (rclpy)."""

    ros_version = 2

    def make_side(self, settings: RosBridgeConfig, node_name: str) -> RosSide:
        """An rclpy node named ``node_name`` in the configured namespace."""
        return Ros2Side(node_name, settings.namespace)
