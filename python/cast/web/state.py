"""The JSON the page draws, from what the servers answered: protobuf messages and the metrics in, plain data out.

One function per part of the page: the architecture (SAs with their
components and the traffic between them), the task managers, the entries of
one WM and one entry's value. docs/web.md says what each figure means.
"""

from __future__ import annotations

from typing import Any

from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import entry_pb2
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.web.feed import task_json
from cast.web.rates import RateWindow

__all__ = ["architecture", "entries_json", "entry_json", "task_managers"]


def _state(value: int) -> str:
    return dir_pb2.ComponentState.Name(value).removeprefix("COMPONENT_STATE_").lower()  # type: ignore[arg-type]


def _seconds(ts: Any) -> float | None:
    return ts.ToNanoseconds() / 1e9 if ts.seconds or ts.nanos else None


def architecture(sas: list[dir_pb2.SubarchitectureInfo], components: list[dir_pb2.ComponentInfo],
                 window: RateWindow, mappings: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """SAs (their WM's size and events/s now), components (language, host, state, restarts) and cross-SA traffic.

    ``mappings``: the rows of bridges' status entries (cast.bridges.status); a
    bridge's component lists its own, with their rates and errors.
    """
    mappings = mappings or []
    events = window.events_per_s()
    within = window.within()
    return {
        "subarchitectures": [{
            "name": sa.name, "endpoint": sa.endpoint, "policy": sa.task_manager_policy, "entries": sa.entries,
            "revision": sa.revision, "bytes": sa.bytes, "max_bytes": sa.max_bytes,
            "events_per_s": events[sa.name][-1][1] if events.get(sa.name) else 0.0,
            "within": within.get(sa.name, {}),
        } for sa in sas],
        "components": [{
            "id": c.id, "subarchitecture": c.subarchitecture, "language": c.language, "kind": c.kind,
            "privileged": c.privileged, "state": _state(c.state), "host": c.host, "pid": c.pid,
            "sessions": c.sessions, "restarts": max(0, c.sessions - 1),
            "mappings": [m for m in mappings if m["bridge"] == c.id],
        } for c in components],
        "traffic": window.traffic(),
        "rates": {"events_per_s": events, "latency": window.latency()},
    }


def task_managers(counters: list[insp_pb2.TaskCounters], tasks: list[tm_pb2.Task],
                  metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """Per SA: the policy, the decision counts, the running (adopted) and waiting tasks, the waiting time."""
    out = []
    for c in counters:
        mine = [task_json(t) for t in tasks if t.subarchitecture == c.subarchitecture]
        wait = metrics.get("subarchitectures", {}).get(c.subarchitecture, {}).get("task_wait", {})
        out.append({
            "subarchitecture": c.subarchitecture, "policy": c.policy, "proposed": c.proposed, "adopted": c.adopted,
            "rejected": c.rejected, "retracted": c.retracted, "completed": c.completed,
            "wait_mean_s": wait.get("mean_s", 0.0), "wait_p90_s": wait.get("p90_s", 0.0),
            "running": [t for t in mine if t["state"] == "adopted"],
            "waiting": [t for t in mine if t["state"] == "waiting"],
        })
    return out


def _entry_head(entry: entry_pb2.Entry) -> dict[str, Any]:
    return {"subarchitecture": entry.address.subarchitecture, "id": entry.address.id, "type": entry.type,
            "version": entry.version, "author": entry.author, "revision": entry.revision,
            "modified": _seconds(entry.modified)}


def entries_json(sa: str, listing: insp_pb2.ListEntriesResponse, total: int, limit: int,
                 types: list[str]) -> dict[str, Any]:
    """One WM's entries, newest write first, with how many it holds in all and the types to filter by."""
    rows = [_entry_head(e) for e in reversed(listing.entries)]
    return {"subarchitecture": sa, "revision": listing.revision, "total": total, "limit": limit,
            "bytes": listing.bytes, "max_bytes": listing.max_bytes, "entries": rows, "types": types}


def entry_json(entry: entry_pb2.Entry, value: Any) -> dict[str, Any]:
    """One entry with its value as JSON."""
    return {**_entry_head(entry), "value": value}
