"""Bridges between the working memories and other middleware: ``ros`` (ROS 2 and ROS 1, docs/ros.md).

A bridge is a component like any other: it uses the public client API only,
and is declared in the system's YAML with its SA, privilege, restart policy
and host.
"""
