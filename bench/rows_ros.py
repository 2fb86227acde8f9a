"""The row of the ROS bridge (bench/ros_bridge.py): M10, ROS publisher -> WM watcher beside ROS -> ROS."""

from __future__ import annotations

from typing import Any

from bench.ros_bridge import HZ, SIZES
from bench.rows import fig

__all__ = ["M10_RATIO", "m10_misses", "m10_row"]

M10_RATIO = 1.5  # target: the bridged p50 at most this many times ROS -> ROS's, measured in the same run


def m10_misses(m10: dict[str, Any]) -> list[str]:
    """What keeps M10 from its target (empty: met)."""
    if "error" in m10:
        return [f"not measured: {m10['error']}"]
    misses = []
    for label in SIZES:
        if label not in m10:
            misses.append(f"{label}: not measured")
            continue
        peer, bridged = m10[label]["ros_ros"], m10[label]["ros_wm"]
        if bridged["p50_us"] > M10_RATIO * peer["p50_us"]:
            misses.append(f"{label}: p50 {bridged['p50_us']:.0f} µs is {bridged['p50_us'] / peer['p50_us']:.1f} x "
                          f"ROS -> ROS's {peer['p50_us']:.0f} µs (target <= {M10_RATIO} x)")
        if bridged["lost"]:
            misses.append(f"{label}: {bridged['lost']} of {bridged['sent']} frames never reached the WM watcher "
                          "and were not reported replaced")
    return misses


def m10_row(m10: dict[str, Any]) -> dict[str, Any]:
    """M10: an rclpy publisher -> the ROS 2 bridge -> a CAST watcher, 1 KiB and 1 MiB at 30 Hz; peer rclpy -> rclpy."""
    figures = []
    for label in SIZES:
        if label not in m10:
            continue
        peer, bridged = m10[label]["ros_ros"], m10[label]["ros_wm"]
        floor = m10[label].get("floor", {}).get("p50_us")
        figures += [
            fig(f"{label}: ROS -> WM p50 (µs)", bridged["p50_us"], peer=peer["p50_us"]),
            fig(f"{label}: ROS -> WM p99 (µs)", bridged["p99_us"], peer=peer["p99_us"]),
            fig(f"{label}: p50 ratio to ROS -> ROS", round(bridged["p50_us"] / peer["p50_us"], 2)),
            fig(f"{label}: lost (ROS -> WM)", bridged["lost"], peer=peer["lost"]),
        ]
        if "ack_p50_us" in bridged:
            figures += [
                fig(f"{label}: stamp -> the bridge's write acknowledged, p50 (µs)", bridged["ack_p50_us"],
                    peer=peer["p50_us"]),
                fig(f"{label}: bare gRPC unary echo at {HZ} Hz, p50 (µs)", floor),
                fig(f"{label}: replaced by a newer frame before written (latest; reported by the bridge)",
                    bridged["replaced"]),
            ]
    misses = m10_misses(m10)
    row: dict[str, Any] = {
        "id": "M10",
        "what": f"ROS 2 publisher (rclpy, sensor_msgs/msg/Image) -> ROS bridge -> WM watcher (Python), 1 KiB and "
        f"1 MiB at {HZ} Hz, {m10.get('count', 0)} frames each; peer: rclpy publisher -> rclpy subscriber, same run",
        "target": f"p50 <= {M10_RATIO} x ROS -> ROS p50; 0 lost",
        "figures": figures,
        "met": not misses,
    }
    if misses:
        row["note"] = "; ".join(misses)
    return row
