"""``cast ls``, ``get``, ``watch``, ``components``, ``tasks`` (and ``stats``): looking at a running system."""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import grpc

from cast.bridges.status import mapping_rows
from cast.cli import stats
from cast.cli.connect import ServerStubs, SystemClient, add_tls_options, connect
from cast.cli.render import SchemaDecoder, iso_time, print_json, print_table
from cast.client.grpc_transport import map_rpc_error
from cast.core.room import mib
from cast.errors import CastError
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import entry_pb2
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.v1 import working_memory_pb2 as wm_pb2

__all__ = ["add_commands"]

OPERATIONS = {"add": entry_pb2.OPERATION_ADD, "overwrite": entry_pb2.OPERATION_OVERWRITE,
              "delete": entry_pb2.OPERATION_DELETE}


def _enum(value: str, prefix: str) -> str:
    return value.removeprefix(prefix).lower()


def _entry_json(entry: entry_pb2.Entry) -> dict[str, Any]:
    return {
        "subarchitecture": entry.address.subarchitecture,
        "id": entry.address.id,
        "type": entry.type,
        "version": entry.version,
        "author": entry.author,
        "revision": entry.revision,
        "modified": iso_time(entry.modified),
    }


# ------------------------------------------------------------------------ ls

def _ls(args: argparse.Namespace) -> int:
    with connect(args) as client:
        sas = [args.subarchitecture] if args.subarchitecture else client.subarchitectures
        rows: list[dict[str, Any]] = []
        held: list[str] = []
        for sa in sas:
            server = client.server(sa)
            req = insp_pb2.ListEntriesRequest(subarchitecture=sa, type=args.type or "", limit=args.limit)
            resp = client.call(server.inspection.ListEntries, req)
            rows.extend(_entry_json(e) for e in resp.entries)
            shared = f", {mib(resp.shared_bytes)} of it in shared memory" if resp.shared_bytes else ""
            held.append(f"{sa} holds {mib(resp.bytes)} of {mib(resp.max_bytes)}{shared}")
    if args.json:
        print_json(rows)
    else:
        print_table(f"{len(rows)} entries ({'; '.join(held)})", ["SA", "id", "type", "version", "author"],
                    [[r["subarchitecture"], r["id"], r["type"], r["version"], r["author"]] for r in rows],
                    numeric=["version"])
    return 0


# ----------------------------------------------------------------------- get

def _get(args: argparse.Namespace) -> int:
    with connect(args) as client:
        server = client.server(args.subarchitecture)
        req = wm_pb2.GetRequest(address=entry_pb2.EntryAddress(id=args.id, subarchitecture=args.subarchitecture))
        entry = client.call(server.wm.Get, req).entry
        out = _entry_json(entry)
        out["value"] = SchemaDecoder(client).to_json(server, entry.type, entry.value.value)
    if args.json:
        print_json(out)
    else:
        from rich.console import Console
        from rich.json import JSON

        console = Console(highlight=False)
        console.print(f"[bold]{out['subarchitecture']}/{out['id']}[/]  {out['type']}  version {out['version']}  "
                      f"by {out['author']}  revision {out['revision']}  {out['modified']}")
        console.print(JSON(json.dumps(out["value"])))
    return 0


# --------------------------------------------------------------------- watch

def _event_json(ev: entry_pb2.ChangeEvent) -> dict[str, Any]:
    return {
        "revision": ev.revision,
        "operation": _enum(entry_pb2.Operation.Name(ev.operation), "OPERATION_"),
        "subarchitecture": ev.address.subarchitecture,
        "id": ev.address.id,
        "type": ev.type,
        "source_component": ev.source_component,
        "source_subarchitecture": ev.source_subarchitecture,
        "version": ev.version,
        "time": iso_time(ev.time),
    }


class _WatchStream:
    """One Watch call to one server; events go to a shared queue."""

    def __init__(self, client: SystemClient, server: ServerStubs, create: wm_pb2.WatchCreate,
                 out: queue.Queue[tuple[ServerStubs, Any]]) -> None:
        self._closed = threading.Event()
        self._server = server
        self._out = out

        def requests() -> Iterator[wm_pb2.WatchRequest]:
            yield wm_pb2.WatchRequest(create=create)
            self._closed.wait()

        self._call = server.wm.Watch(requests(), metadata=client.metadata)
        threading.Thread(target=self._read, daemon=True, name=f"cast-watch-{server.endpoint}").start()

    def _read(self) -> None:
        try:
            for resp in self._call:
                if resp.HasField("failed"):
                    self._out.put((self._server, CastError(f"{resp.failed.code}: {resp.failed.message}")))
                    return
                for ev in resp.events:
                    self._out.put((self._server, ev))
            self._out.put((self._server, None))
        except grpc.RpcError as exc:
            if not self._closed.is_set():
                self._out.put((self._server, map_rpc_error(exc)))

    def close(self) -> None:
        self._closed.set()
        self._call.cancel()  # type: ignore[no-untyped-call]


def _watch(args: argparse.Namespace) -> int:
    ops = [OPERATIONS[o] for o in args.op or []]
    with connect(args) as client:
        sas = args.subarchitecture or client.subarchitectures
        events: queue.Queue[tuple[ServerStubs, Any]] = queue.Queue()
        streams = []
        for server, hosted in client.servers():
            mine = [sa for sa in sas if sa in hosted]
            if not mine:
                continue
            filters = [entry_pb2.ChangeFilter(operations=ops, type=args.type or "", id=args.id or "",
                                              subarchitecture=sa, source_component=args.source or "",
                                              include_entry=args.values) for sa in mine]
            starts = {sa: args.from_revision for sa in mine} if args.from_revision else {}
            create = wm_pb2.WatchCreate(watch_id=1, filters=filters, start_revisions=starts)
            streams.append(_WatchStream(client, server, create, events))
        for sa in sas:
            client.server(sa)  # NOT_FOUND for an unknown SA, before waiting for anything
        decoder = SchemaDecoder(client) if args.values else None
        deadline = time.monotonic() + args.for_seconds if args.for_seconds else None
        count = 0
        try:
            while args.count == 0 or count < args.count:
                timeout = None if deadline is None else deadline - time.monotonic()
                if timeout is not None and timeout <= 0:
                    break
                try:
                    server, item = events.get(timeout=timeout if timeout is not None else 0.5)
                except queue.Empty:
                    continue
                if item is None:
                    continue
                if isinstance(item, CastError):
                    raise item
                out = _event_json(item)
                if decoder is not None and item.HasField("entry"):
                    out["value"] = decoder.to_json(server, item.entry.type, item.entry.value.value)
                sys.stdout.write(json.dumps(out) + "\n")
                sys.stdout.flush()
                count += 1
        finally:
            for stream in streams:
                stream.close()
    return 0


# ---------------------------------------------------------------- components

def _components(args: argparse.Namespace) -> int:
    with connect(args) as client:
        desc = client.call(client.directory.directory.DescribeSystem, dir_pb2.DescribeSystemRequest())
        # What each component holds, summed over every server of the system.
        held: dict[str, list[int]] = {}
        for server, _ in client.servers():
            other = client.call(server.directory.DescribeSystem, dir_pb2.DescribeSystemRequest())
            for c in other.components:
                usage = held.setdefault(c.id, [0, 0])
                usage[0] += c.entries
                usage[1] += c.bytes
        mappings = mapping_rows(stats.bridge_statuses(client))
    rows = [{
        "id": c.id, "subarchitecture": c.subarchitecture, "language": c.language,
        "library_version": c.library_version, "kind": c.kind,
        "privileged": c.privileged, "state": _enum(dir_pb2.ComponentState.Name(c.state), "COMPONENT_STATE_"),
        "pid": c.pid, "host": c.host, "sessions": c.sessions,
        "entries": held.get(c.id, [0, 0])[0], "bytes": held.get(c.id, [0, 0])[1],
    } for c in desc.components]
    for row in rows:
        mine = [m for m in mappings if m["bridge"] == row["id"]]
        if mine:
            row["mappings"] = mine
    if args.json:
        print_json(rows)
    else:
        print_table(f"system '{desc.name}': {len(rows)} components",
                    ["id", "SA", "language", "library", "kind", "privileged", "state", "pid", "host", "sessions",
                     "entries", "holds"],
                    [[r["id"], r["subarchitecture"], r["language"], r["library_version"], r["kind"],
                      "yes" if r["privileged"] else "",
                      r["state"], r["pid"] or "", r["host"], r["sessions"], r["entries"], mib(r["bytes"])]
                     for r in rows],
                    numeric=["pid", "sessions", "entries", "holds"])
        if mappings:
            print_table(f"{len(mappings)} bridge mappings (docs/ros.md)",
                        ["bridge", "direction", "topic", "ROS type", "SA", "entry", "received", "delivered",
                         "dropped", "errors", "rate/s", "pending", "last error"],
                        [[m["bridge"], m["direction"], m["topic"], m["ros_type"], m["subarchitecture"], m["entry"],
                          m["received"], m["delivered"], m["dropped"], m["errors"], f"{m['rate_hz']:.1f}",
                          m["pending"], m["last_error"]] for m in mappings],
                        numeric=["received", "delivered", "dropped", "errors", "rate/s", "pending"])
    return 0



# --------------------------------------------------------------------- tasks

def _tasks(args: argparse.Namespace) -> int:
    with connect(args) as client:
        sa = args.subarchitecture or ""
        servers = [(client.server(sa), [sa])] if sa else client.servers()
        tasks: list[dict[str, Any]] = []
        counters: list[dict[str, Any]] = []
        for server, _ in servers:
            listed = client.call(server.tm.ListTasks, tm_pb2.ListTasksRequest(subarchitecture=sa))
            tasks.extend({
                "task_id": t.task_id, "subarchitecture": t.subarchitecture, "name": t.name,
                "component": t.component, "state": _enum(tm_pb2.TaskState.Name(t.state), "TASK_STATE_"),
                "priority": t.priority, "proposed": iso_time(t.proposed),
            } for t in listed.tasks)
            stats = client.call(server.inspection.TaskStatistics, insp_pb2.TaskStatisticsRequest(subarchitecture=sa))
            counters.extend({
                "subarchitecture": c.subarchitecture, "policy": c.policy, "proposed": c.proposed,
                "adopted": c.adopted, "rejected": c.rejected, "retracted": c.retracted, "completed": c.completed,
            } for c in stats.subarchitectures)
    if args.json:
        print_json({"tasks": tasks, "subarchitectures": counters})
        return 0
    print_table("task managers", ["SA", "policy", "proposed", "adopted", "rejected", "retracted", "completed"],
                [[c["subarchitecture"], c["policy"], c["proposed"], c["adopted"], c["rejected"], c["retracted"],
                  c["completed"]] for c in counters],
                numeric=["proposed", "adopted", "rejected", "retracted", "completed"])
    print_table(f"{len(tasks)} live tasks", ["task", "SA", "name", "component", "state", "priority"],
                [[t["task_id"], t["subarchitecture"], t["name"], t["component"], t["state"], t["priority"]]
                 for t in tasks], numeric=["priority"])
    return 0


# ------------------------------------------------------------------- parsers

def _common(p: argparse.ArgumentParser, json_flag: bool = True) -> None:
    p.add_argument("--endpoint", help="directory HOST:PORT (default: $CAST_ENDPOINT, else the running `cast run`)")
    p.add_argument("--runtime-dir", help="runtime directory of the running `cast run` (default: $CAST_RUNTIME_DIR "
                                         "or .cast)")
    p.add_argument("--secret-file", help="token secret (default: $CAST_SECRET, else the runtime directory's)")
    add_tls_options(p)
    if json_flag:
        p.add_argument("--json", action="store_true", help="JSON for scripts instead of a table")


def add_commands(sub: Any) -> None:
    """Add the inspection subcommands to the ``cast`` parser."""
    ls = sub.add_parser("ls", help="list the entries of one SA (or all): id, type, version, author")
    ls.add_argument("subarchitecture", nargs="?", help="SA to list (default: every SA)")
    ls.add_argument("--type", help="only entries of this full message name")
    ls.add_argument("--limit", type=int, default=0, help="at most this many entries per SA (most recent)")
    _common(ls)
    ls.set_defaults(fn=_ls)

    get = sub.add_parser("get", help="show one entry, its value rendered as JSON through its registered schema")
    get.add_argument("subarchitecture", help="the entry's SA")
    get.add_argument("id", help="the entry's id")
    _common(get)
    get.set_defaults(fn=_get)

    watch = sub.add_parser("watch", help="print change events as they happen, one JSON line each")
    watch.add_argument("--sa", dest="subarchitecture", action="append", help="SA to watch (repeatable; default: all)")
    watch.add_argument("--type", help="only entries of this full message name")
    watch.add_argument("--op", action="append", choices=sorted(OPERATIONS), help="only these operations (repeatable)")
    watch.add_argument("--id", help="only this entry id")
    watch.add_argument("--source", help="only writes by this component")
    watch.add_argument("--from", dest="from_revision", type=int, default=0,
                       help="start at this revision (of each SA watched) instead of now")
    watch.add_argument("--values", action="store_true", help="add each entry's value as JSON")
    watch.add_argument("--count", type=int, default=0, help="exit after this many events")
    watch.add_argument("--for", dest="for_seconds", type=float, default=0, help="exit after this many seconds")
    _common(watch, json_flag=False)
    watch.add_argument("--json", action="store_true", help="accepted for symmetry: the output is always JSON lines")
    watch.set_defaults(fn=_watch)

    comps = sub.add_parser("components", help="list the components and their state")
    _common(comps)
    comps.set_defaults(fn=_components)

    tasks = sub.add_parser("tasks", help="the task managers' counts and the live tasks")
    tasks.add_argument("subarchitecture", nargs="?", help="SA (default: every SA)")
    _common(tasks)
    tasks.set_defaults(fn=_tasks)

    stats.add_command(sub, _common)
