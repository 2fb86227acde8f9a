"""What a recording holds: SAs, types, counts per channel and operation, time span, gaps (``cast info``)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from cast.recording.channels import ROLE_CHANGES, ROLE_GAPS, SCHEMA_KEY
from cast.recording.reading import Recording

__all__ = ["describe", "iso"]


def iso(ns: int) -> str:
    """Nanoseconds since the epoch as ISO 8601 in UTC, to the millisecond; empty for 0."""
    if not ns:
        return ""
    return datetime.fromtimestamp(ns / 1e9, tz=UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def describe(recording: Recording) -> dict[str, Any]:
    """A JSON-ready description of a recording.

    Channel counts come from the summary; the counts per operation and the
    revisions per SA from reading the change records (values are skipped).
    """
    per_sa: dict[str, dict[str, Any]] = {
        sa: {"subarchitecture": sa, "changes": 0, "add": 0, "overwrite": 0, "delete": 0, "first_revision": 0,
             "last_revision": 0}
        for sa in recording.subarchitectures
    }
    for recorded in recording.changes(topics=()):
        change = recorded.change
        row = per_sa.setdefault(change.subarchitecture, {
            "subarchitecture": change.subarchitecture, "changes": 0, "add": 0, "overwrite": 0, "delete": 0,
            "first_revision": 0, "last_revision": 0})
        row["changes"] += 1
        row[change.operation.name.lower()] += 1
        row["first_revision"] = row["first_revision"] or change.revision
        row["last_revision"] = change.revision
    start, end = recording.start_ns, recording.end_ns
    header, trailer = recording.header, recording.trailer
    changes = sum(recording.count(c) for c in recording.channels(ROLE_CHANGES))
    return {
        "file": str(recording.path),
        "system": header.get("system", ""),
        "endpoint": header.get("endpoint", ""),
        "recorded_from": header.get("started", ""),
        "recorded_to": trailer.get("stopped", ""),
        "stop_reason": trailer.get("reason", ""),
        "types_filter": [t for t in header.get("types", "").split(",") if t],
        "start": iso(start),
        "end": iso(end),
        "duration_s": round(max(0, end - start) / 1e9, 6),
        "changes": changes,
        "subarchitectures": list(per_sa.values()),
        "channels": [
            {"topic": c.topic, "subarchitecture": sa, "type": type_name, "messages": recording.count(c),
             "schema": c.metadata.get(SCHEMA_KEY, "")}
            for (sa, type_name), c in recording.value_channels().items()
        ] + [
            {"topic": c.topic, "subarchitecture": "", "type": c.metadata.get("cast.role", ""),
             "messages": recording.count(c), "schema": "registered"}
            for c in recording.channels(ROLE_CHANGES) + recording.channels(ROLE_GAPS)
        ],
        "gaps": [
            {"subarchitecture": g.subarchitecture, "last_revision": g.last_revision,
             "resumed_revision": g.resumed_revision, "missing": g.missing, "reason": g.reason, "time": iso(g.time_ns),
             "history_before": g.history_before, "history_after": g.history_after}
            for g in recording.gaps()
        ],
    }
