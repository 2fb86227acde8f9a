"""M10's row: the bridged path against rclpy -> rclpy, and what counts as lost."""

from __future__ import annotations

from typing import Any

from bench.ros_bridge import _figures
from bench.rows_ros import m10_misses, m10_row


def _m10(bridged_p50: float, peer_p50: float = 1000.0, lost: int = 0, replaced: int = 0) -> dict[str, Any]:
    def side(p50: float, lost_: int, replaced_: int) -> dict[str, Any]:
        return {"p50_us": p50, "p99_us": 2 * p50, "sent": 90, "received": 90 - lost_ - replaced_, "lost": lost_,
                "replaced": replaced_, "ack_p50_us": p50 * 0.8, "ack_p99_us": p50}

    size = {"ros_ros": side(peer_p50, 0, 0), "ros_wm": side(bridged_p50, lost, replaced),
            "floor": {"p50_us": 500.0}}
    return {"count": 90, "hz": 30, "1 KiB": size, "1 MiB": size}


def test_m10_is_met_at_one_and_a_half_times_ros_to_ros_with_nothing_lost() -> None:
    assert m10_misses(_m10(1500)) == [] and m10_row(_m10(1500))["met"]
    assert any("1.5 x" in m for m in m10_misses(_m10(1501)))
    assert any("never reached" in m for m in m10_misses(_m10(1000, lost=1)))


def test_frames_the_bridge_reported_replaced_are_shown_and_not_lost() -> None:
    assert m10_misses(_m10(1000, replaced=3)) == []
    figures = {f["name"]: f["value"] for f in m10_row(_m10(1000, replaced=3))["figures"]}
    assert figures["1 KiB: replaced by a newer frame before written (latest; reported by the bridge)"] == 3
    assert figures["1 KiB: bare gRPC unary echo at 30 Hz, p50 (µs)"] == 500.0
    assert figures["1 KiB: stamp -> the bridge's write acknowledged, p50 (µs)"] == 800.0


def test_missing_frames_beyond_those_reported_replaced_are_lost() -> None:
    sent = {i: 0 for i in range(10)}
    arrived = {i: 1000 for i in range(7)}
    assert _figures(sent, arrived, replaced=2)["lost"] == 1
    assert _figures(sent, arrived, replaced=0)["lost"] == 3
    assert _figures(sent, arrived, replaced=5)["lost"] == 0
