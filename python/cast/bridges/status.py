"""Bridges' status entries (``cast.v1.BridgeStatus``) as rows: what `cast components`, `cast stats`, the web view show.

A bridge writes its status into its own SA (``<component id>.status``); a
tool reads every entry of the type from every WM (``GetByType``) and turns
each mapping into one plain row here, so that the three show the same
figures under the same names.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from cast.v1 import bridge_pb2, entry_pb2

__all__ = ["STATUS_TYPE", "mapping_rows", "statuses_of"]

STATUS_TYPE = bridge_pb2.BridgeStatus.DESCRIPTOR.full_name


def statuses_of(entries: Iterable[entry_pb2.Entry]) -> list[bridge_pb2.BridgeStatus]:
    """The bridge statuses among entries read with ``GetByType(STATUS_TYPE)`` (values that do not parse are skipped)."""
    out = []
    for entry in entries:
        status = bridge_pb2.BridgeStatus()
        if entry.value.Unpack(status):
            out.append(status)
    return sorted(out, key=lambda s: s.bridge)


def _time(ts: Any) -> float | None:
    return ts.ToNanoseconds() / 1e9 if ts.seconds or ts.nanos else None


def mapping_rows(statuses: Iterable[bridge_pb2.BridgeStatus]) -> list[dict[str, Any]]:
    """One row per mapping of every bridge: its ends, its counts, its rate and errors, ROS -> WM latency."""
    rows = []
    for s in statuses:
        for m in s.mappings:
            rows.append({
                "bridge": s.bridge, "middleware": s.middleware, "node": s.node, "status_time": _time(s.time),
                "reconnections": s.reconnections, "direction": m.direction, "topic": m.topic, "ros_type": m.ros_type,
                "entry_type": m.entry_type, "subarchitecture": m.subarchitecture, "entry": m.entry,
                "received": m.received, "delivered": m.delivered, "dropped": m.dropped, "errors": m.errors,
                "rate_hz": m.rate_hz, "pending": m.pending, "last_error": m.last_error,
                "last_error_time": _time(m.last_error_time), "last_time": _time(m.last_time),
                "latency_count": m.latency_count, "latency_p50_s": m.latency_p50_seconds,
                "latency_p99_s": m.latency_p99_seconds, "latency_max_s": m.latency_max_seconds,
            })
    return rows
