"""The ROS 1 side of the bridge: a rospy node (``Ros1Bridge``), which registers again with a master that restarted.

rospy talks to the master (``ROS_MASTER_URI``) only to register and look
up; messages then flow over direct TCP connections between nodes, which a
master restart does not cut. But a new master knows nothing of the nodes
registered with the old one, and rospy never registers again by itself: a
publisher started after the restart would never be told about the bridge.
So ``poll`` asks the master its pid every status period, and when it
changed, registers every subscription and publication of the bridge again
through the master's API, passing the publishers it names to the node's
own ``publisherUpdate``, as the master itself would.

rospy imports only in the interpreter it was built for (Debian's
``/usr/bin/python3``): the launcher runs the bridge with that one.
"""

from __future__ import annotations

import os
import sys
import xmlrpc.client
from collections.abc import Callable
from typing import Any

from cast.bridges.ros.bridge import RosBridge, RosSide
from cast.config.ros import RosBridgeConfig, RosQos

__all__ = ["Ros1Bridge", "Ros1Side"]


class Ros1Side:
    """A rospy node, its subscribers and publishers, and the master it registered with."""

    def __init__(self, node_name: str, namespace: str) -> None:
        import rospy

        self._rospy = rospy
        argv = [sys.argv[0]] + ([f"__ns:={namespace}"] if namespace else [])
        rospy.init_node(node_name, argv=argv, anonymous=False, disable_signals=True)
        self.node_name = rospy.get_name()
        self.master_uri = os.environ.get("ROS_MASTER_URI", "http://localhost:11311")
        self.middleware = f"ROS 1 (rospy, master {self.master_uri})"
        self._subscribed: list[tuple[str, str]] = []  # (resolved topic, type)
        self._advertised: list[tuple[str, str]] = []
        self._held: list[Any] = []
        self._master_pid = self._pid()

    def _master(self) -> Any:
        return xmlrpc.client.ServerProxy(self.master_uri)

    def _pid(self) -> int | None:
        try:
            code, _, pid = self._master().getPid(self.node_name)
        except (OSError, xmlrpc.client.Error):
            return None
        return int(pid) if code == 1 else None

    def subscribe(self, topic: str, cls: Any, qos: RosQos, callback: Callable[[Any], None]) -> None:
        """A subscriber (queue of ``depth`` messages, TCP_NODELAY) calling ``callback`` on rospy's thread."""
        sub = self._rospy.Subscriber(topic, cls, callback, queue_size=qos.depth, tcp_nodelay=True)
        self._held.append(sub)
        self._subscribed.append((sub.resolved_name, cls._type))

    def advertise(self, topic: str, cls: Any, qos: RosQos) -> Callable[[Any], None]:
        """A publisher (latched when the QoS durability is transient_local); its ``publish``."""
        pub = self._rospy.Publisher(topic, cls, queue_size=qos.depth, latch=qos.durability == "transient_local")
        self._held.append(pub)
        self._advertised.append((pub.resolved_name, cls._type))
        return pub.publish  # type: ignore[no-any-return]

    def poll(self) -> bool:
        """Register everything again when the master is a new one (its pid changed); whether it did."""
        pid = self._pid()
        if pid is None or pid == self._master_pid:
            return False
        caller, uri = self.node_name, self._rospy.core.get_node_uri()
        master = self._master()
        for topic, type_name in self._advertised:
            master.registerPublisher(caller, topic, type_name, uri)
        node = xmlrpc.client.ServerProxy(uri)
        for topic, type_name in self._subscribed:
            code, _, publishers = master.registerSubscriber(caller, topic, type_name, uri)
            if code == 1:
                node.publisherUpdate("/master", topic, publishers)
        self._master_pid = pid
        return True

    def close(self) -> None:
        """Unregister and leave."""
        for held in self._held:
            held.unregister()
        self._rospy.signal_shutdown("the CAST bridge stopped")


class Ros1Bridge(RosBridge):
    """The ROS bridge for ROS 1 (rospy)."""

    ros_version = 1

    def make_side(self, settings: RosBridgeConfig, node_name: str) -> RosSide:
        """A rospy node named ``node_name`` in the configured namespace."""
        return Ros1Side(node_name, settings.namespace)
