"""``cast stats``: what the servers of a running system counted (docs/experiments.md, "Metrics").

Every server is asked (``Inspection.GetMetrics``) and the answers merged into
one system's metrics: tables by default, ``--json`` the shape that
``cast run --summary-json`` also writes under ``metrics``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from cast.bridges.status import STATUS_TYPE, mapping_rows, statuses_of
from cast.cli.connect import SystemClient, connect
from cast.cli.render import print_json, print_table
from cast.core.metrics_view import merge_snapshots
from cast.v1 import bridge_pb2
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire.metrics import snapshot_from_pb

__all__ = ["add_command", "bridge_statuses", "system_metrics"]

NO_SA = "(none)"
"""How the tables show the SA of a caller that belongs to none (a tool, a script)."""


def system_metrics(client: SystemClient) -> dict[str, Any]:
    """The merged metrics of every server of the system ``client`` reaches."""
    snapshots = [snapshot_from_pb(client.call(server.inspection.GetMetrics, insp_pb2.GetMetricsRequest()))
                 for server, _ in client.servers()]
    return merge_snapshots(snapshots)


def bridge_statuses(client: SystemClient) -> list[bridge_pb2.BridgeStatus]:
    """The status entry of every bridge of the system (``cast.v1.BridgeStatus``, in any SA: docs/ros.md)."""
    entries = []
    for server, hosted in client.servers():
        for sa in hosted:
            # A listing of the status type only (a read of the tool's, counted as such), then the statuses.
            listed = client.call(server.inspection.ListEntries,
                                 insp_pb2.ListEntriesRequest(subarchitecture=sa, type=STATUS_TYPE))
            if listed.entries:
                request = wm_pb2.GetByTypeRequest(subarchitecture=sa, type=STATUS_TYPE)
                entries.extend(client.call(server.wm.GetByType, request).entries)
    return statuses_of(entries)


def _ms(seconds: float) -> str:
    return f"{seconds * 1000:.2f}"


def _size(n: int) -> str:
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def _sa(name: str) -> str:
    return name or NO_SA


def _counter_row(c: dict[str, Any]) -> list[Any]:
    adopted = c["tasks_adopted"]
    return [c["reads"], f"{c['adds']}/{c['overwrites']}/{c['deletes']}", _size(c["bytes_in"]), _size(c["bytes_out"]),
            c["events"], c["locks"], f"{c['lock_waits']} ({_ms(c['lock_wait_s'])} ms)",
            f"{c['tasks_proposed']}/{adopted}/{c['tasks_rejected']}/{c['tasks_completed']}",
            _ms(c["task_wait_s"] / adopted) if adopted else ""]


def _hist_row(h: dict[str, Any]) -> list[Any]:
    return [h["count"], _ms(h["mean_s"]), _ms(h["p50_s"]), _ms(h["p90_s"]), _ms(h["p99_s"])]


_COUNTER_COLUMNS = ["reads", "writes a/o/d", "in", "out", "events", "locks", "lock waits", "tasks p/a/r/c",
                    "task wait ms"]


def _print_tables(m: dict[str, Any]) -> None:
    note = "" if m["enabled"] else " (a server counts nothing: --no-metrics)"
    print(f"system '{m['system']}': counted by {m['servers']} server(s), up {m['uptime_s']:.1f} s{note}")
    comps = m["components"]
    print_table(f"{len(comps)} components", ["component", "SA", *_COUNTER_COLUMNS, "refused"],
                [[cid, _sa(c["subarchitecture"]), *_counter_row(c), c["writes_refused"]] for cid, c in comps.items()],
                numeric=["reads", "events", "locks", "task wait ms", "refused"])
    wms = m["subarchitectures"]
    print_table("working memories (calls into each)", ["SA", *_COUNTER_COLUMNS],
                [[sa, *_counter_row(c)] for sa, c in wms.items()], numeric=["reads", "events", "locks", "task wait ms"])
    froms = sorted({cell["from_sa"] for cell in m["traffic"]})
    tos = list(wms) + sorted({cell["to_sa"] for cell in m["traffic"]} - set(wms))
    cells = {(cell["from_sa"], cell["to_sa"]): cell for cell in m["traffic"]}

    def cell(a: str, b: str) -> str:
        found = cells.get((a, b))
        return "" if found is None else f"{found['reads']} / {found['writes']}"

    print_table("traffic (reads / writes): caller's SA down, WM across", ["from \\ to", *tos],
                [[_sa(a), *(cell(a, b) for b in tos)] for a in froms], numeric=tos)
    watchers = m["delivery_latency"]["watchers"]
    print_table("write -> event delivery latency (ms; quantiles estimated from buckets)",
                ["watcher", "SA", "events", "mean", "p50", "p90", "p99"],
                [*([w, _sa(h["subarchitecture"]), *_hist_row(h)] for w, h in watchers.items()),
                 ["all", "", *_hist_row(m["delivery_latency"]["all"])]],
                numeric=["events", "mean", "p50", "p90", "p99"])
    shared = m.get("shared_memory")
    if shared:
        print_table("shared memory (values of at least " + _size(shared["threshold_bytes"]) + ")",
                    ["segments", "values held", "lent now", "sessions", "staged writes", "lent", "unplaced",
                     "over window"],
                    [[f"{shared['segments']} ({_size(shared['segment_bytes'])} of {_size(shared['max_bytes'])})",
                      f"{shared['values']} ({_size(shared['value_bytes'])})", _size(shared["lent_bytes"]),
                      shared["sessions"], f"{shared['staged_writes']} ({_size(shared['staged_bytes'])})",
                      f"{shared['lent']} ({_size(shared['lent_total_bytes'])})", shared["unplaced"],
                      shared["over_window"]]],
                    numeric=["sessions", "unplaced", "over window"])
    else:
        print("shared memory: off")
    reports = [[cid, name, r["count"], f"{r['sum']:g}", f"{r['min']:g}", f"{r['max']:g}", f"{r['mean']:g}",
                f"{r['last']:g}"] for cid, named in m["reports"].items() for name, r in named.items()]
    if reports:
        print_table("reported by components", ["component", "name", "count", "sum", "min", "max", "mean", "last"],
                    reports, numeric=["count", "sum", "min", "max", "mean", "last"])


def _print_bridges(rows: list[dict[str, Any]]) -> None:
    inbound = [r for r in rows if r["direction"] == "to_wm"]
    if inbound:
        print_table("ROS -> WM latency (ms: header stamp, or receipt, -> write acknowledged; the last 1,000 "
                    "messages of each bridge mapping)",
                    ["bridge", "topic", "SA", "entry", "messages", "p50", "p99", "max", "rate/s", "dropped", "errors"],
                    [[r["bridge"], r["topic"], r["subarchitecture"], r["entry"], r["delivered"],
                      _ms(r["latency_p50_s"]), _ms(r["latency_p99_s"]), _ms(r["latency_max_s"]), f"{r['rate_hz']:.1f}",
                      r["dropped"], r["errors"]] for r in inbound],
                    numeric=["messages", "p50", "p99", "max", "rate/s", "dropped", "errors"])


def _stats(args: argparse.Namespace) -> int:
    with connect(args) as client:
        metrics = system_metrics(client)
        bridges = mapping_rows(bridge_statuses(client))
    if args.json:
        # The shape of `cast run --summary-json`'s metrics, and the bridges' mappings when there are any.
        print_json({**metrics, "bridges": bridges} if bridges else metrics)
    else:
        _print_tables(metrics)
        _print_bridges(bridges)
    return 0


def add_command(sub: Any, common: Callable[[argparse.ArgumentParser], None]) -> None:
    """Add ``cast stats``; ``common`` adds the options every inspection command shares."""
    stats = sub.add_parser("stats", help="what the servers counted: per component and WM, the cross-SA traffic, "
                                         "delivery latency, reported outcomes (docs/experiments.md)")
    common(stats)
    stats.set_defaults(fn=_stats)
