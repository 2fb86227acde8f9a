"""What the live status view and the final summary show, and how they look.

A :class:`Snapshot` is taken from the servers' own objects (the orchestrator
hosts them) and the supervisor's records; rendering it is separate, so the
summary printed at the end and ``--summary-json`` use the same numbers.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import grpc
from rich.console import Group, RenderableType
from rich.table import Table
from rich.text import Text

from cast.config.model import SystemConfig
from cast.core.describe import SystemSummary, describe
from cast.core.sessions import ComponentState
from cast.orchestrator.servers import ServerGroup
from cast.orchestrator.supervisor import Supervisor
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc
from cast.wire.describe import summary_from_pb

__all__ = ["ComponentRow", "Snapshot", "StatusTracker", "SubarchitectureRow", "render_status", "render_summary"]


@dataclass
class ComponentRow:
    """One component as the status view shows it."""

    id: str
    subarchitecture: str
    language: str
    kind: str
    launch: str  # process, in-process, manual, joined
    phase: str  # orchestrator's view: running, restarting, failed, ...
    session: str  # server's view: expected, starting, started, running, stopping, disconnected
    pid: int
    restarts: int
    sessions: int
    crashes: list[int] = field(default_factory=list)
    host: str = "local"  # where it runs: local (the orchestrator's host) or a name under hosts:


@dataclass
class SubarchitectureRow:
    """One SA: its WM and its task manager."""

    name: str
    endpoint: str
    policy: str
    entries: int
    revision: int
    events_per_s: float
    waiting: int
    running: int
    counters: dict[str, int]
    types: dict[str, int]


@dataclass
class Snapshot:
    """The whole system at one moment."""

    system: str
    endpoint: str
    uptime: float
    components: list[ComponentRow]
    subarchitectures: list[SubarchitectureRow]
    multihost: bool = False  # the system has hosts: (the tables get a host column)

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready form."""
        return asdict(self)


class StatusTracker:
    """Takes snapshots; remembers the last revisions to compute events per second."""

    def __init__(self, config: SystemConfig, servers: ServerGroup, supervisor: Supervisor) -> None:
        self._config = config
        self._servers = servers
        self._supervisor = supervisor
        self._started = time.monotonic()
        self._last: tuple[float, dict[str, int]] | None = None
        self._remote_rows: list[SubarchitectureRow] = []  # the SAs of servers on other hosts (refresh_remote)
        self._remote_at = 0.0

    def snapshot(self) -> Snapshot:
        """The current state of everything."""
        now = time.monotonic()
        directory = self._servers.directory.system
        rows: list[ComponentRow] = []
        configured = {c.id: c for c in self._config.components}
        for info in directory.sessions.components():
            comp = configured.get(info.id)
            sup = self._supervisor.components.get(info.id)
            if comp is None:
                launch, phase = "joined", "-"
            elif comp.in_process:
                launch, phase = "in-process", "running" if info.session_id else "-"
            elif comp.manual:
                launch, phase = "manual", "-"
            else:
                launch, phase = "process", sup.phase.value if sup is not None else "-"
            rows.append(ComponentRow(
                id=info.id,
                subarchitecture=info.subarchitecture,
                language=info.language or (comp.language if comp else ""),
                kind=info.kind or (comp.kind if comp else ""),
                launch=launch,
                phase=phase,
                session=ComponentState(info.state).name.lower(),
                pid=(sup.pid if sup is not None and sup.pid else info.pid if info.session_id else 0),
                restarts=sup.restarts if sup is not None else 0,
                sessions=info.sessions,
                crashes=list(sup.crashes) if sup is not None else [],
                host=comp.host if comp is not None else info.host,
            ))
        elapsed = now - self._last[0] if self._last else 0.0
        local = self._local_rows()
        revisions = {sa.name: sa.revision for sa in local}
        for sa in local:
            before = self._last[1].get(sa.name, sa.revision) if self._last else sa.revision
            sa.events_per_s = (sa.revision - before) / elapsed if elapsed > 0 else 0.0
        self._last = (now, revisions)
        sas = [*local, *(replace(r) for r in self._remote_rows)]  # remote rates: per refresh (refresh_remote)
        return Snapshot(self._config.name, self._servers.directory.endpoint, now - self._started, rows, sas,
                        bool(self._config.hosts))

    def _local_rows(self) -> list[SubarchitectureRow]:
        """The SAs of the servers in this process, described by their objects (cast.core.describe)."""
        sas: list[SubarchitectureRow] = []
        for server in self._servers.servers:
            routes = server.running.routes
            sas += _rows(describe(server.system, routes.endpoint, routes.local))
        return sas

    async def refresh_remote(self) -> None:
        """Ask each server on another host to describe itself (``DescribeSystem``, read back by cast.wire.describe).

        Their objects live in another process, so the live view shows what the last refresh found; a server
        that does not answer keeps its last rows.
        """
        now = time.monotonic()
        before = {r.name: r.revision for r in self._remote_rows}
        elapsed = now - self._remote_at if self._remote_rows else 0.0
        rows: list[SubarchitectureRow] = []
        for far in self._servers.remote:
            if not far.process.running:
                continue
            try:
                async with self._servers.remote_channel(far) as channel:
                    described = await directory_pb2_grpc.DirectoryStub(channel).DescribeSystem(
                        dir_pb2.DescribeSystemRequest(), metadata=self._servers.orchestrator_metadata(), timeout=2.0)
            except grpc.RpcError:
                rows += [r for r in self._remote_rows if r.endpoint == far.address]
                continue
            found = _rows(summary_from_pb(described), far.address)
            for row in found:
                if elapsed > 0 and row.name in before:
                    row.events_per_s = (row.revision - before[row.name]) / elapsed
            rows += found
        self._remote_rows, self._remote_at = rows, now


def _rows(summary: SystemSummary, endpoint: str = "") -> list[SubarchitectureRow]:
    """The rows of the SAs a server described as its own (``endpoint``: shown for each, else their own)."""
    return [
        SubarchitectureRow(
            name=sa.name, endpoint=endpoint or sa.endpoint, policy=sa.policy, entries=sa.entries, revision=sa.revision,
            events_per_s=0.0, waiting=sa.waiting, running=sa.adopted, counters=dict(sa.counters), types=dict(sa.types),
        )
        for sa in summary.subarchitectures if sa.hosted
    ]


_PHASE_STYLE = {"running": "green", "restarting": "yellow", "failed": "bold red", "exited": "dim",
                "stopping": "yellow", "stopped": "dim", "pending": "dim"}
_SESSION_STYLE = {"running": "green", "starting": "yellow", "started": "cyan", "expected": "dim", "stopping": "yellow",
                  "disconnected": "red"}


def _components_table(snap: Snapshot) -> Table:
    table = Table(title="components", title_justify="left", expand=False)
    cols = ["id", "SA", "lang", "kind", *(["host"] if snap.multihost else []), "launch", "process", "session", "pid",
            "restarts"]
    for col in cols:
        table.add_column(col, justify="right" if col in ("pid", "restarts") else "left")
    for c in snap.components:
        table.add_row(
            c.id, c.subarchitecture, c.language, c.kind, *([c.host] if snap.multihost else []), c.launch,
            Text(c.phase, style=_PHASE_STYLE.get(c.phase, "")),
            Text(c.session, style=_SESSION_STYLE.get(c.session, "")),
            str(c.pid or ""), str(c.restarts or ""),
        )
    return table


def _sa_table(snap: Snapshot, live: bool) -> Table:
    table = Table(title="subarchitectures", title_justify="left", expand=False)
    cols = ["SA", "policy", "entries", "events"]
    if live:
        cols += ["events/s", "waiting", "running"]
    cols += ["proposed", "adopted", "rejected", "completed"]
    for col in cols:
        table.add_column(col, justify="left" if col in ("SA", "policy") else "right")
    for sa in snap.subarchitectures:
        row = [sa.name, sa.policy, str(sa.entries), str(sa.revision)]
        if live:
            row += [f"{sa.events_per_s:.1f}", str(sa.waiting), str(sa.running)]
        row += [str(sa.counters.get(k, 0)) for k in ("proposed", "adopted", "rejected", "completed")]
        table.add_row(*row)
    return table


def render_status(snap: Snapshot) -> RenderableType:
    """The live view: a header line, the components and the SAs."""
    header = Text.assemble(
        ("cast run ", "bold"), (snap.system, "bold cyan"), f"  {snap.endpoint}  up {snap.uptime:.0f} s  ",
        ("(Ctrl-C stops)", "dim"),
    )
    return Group(header, _components_table(snap), _sa_table(snap, live=True))


def render_summary(snap: Snapshot, failures: list[str]) -> RenderableType:
    """The summary printed at the end of a run."""
    parts: list[RenderableType] = [
        Text.assemble(("summary of ", "bold"), (snap.system, "bold cyan"), f" after {snap.uptime:.1f} s"),
        _sa_table(snap, live=False),
    ]
    if snap.multihost:
        hosts: dict[str, list[str]] = {}
        for c in snap.components:
            hosts.setdefault(c.host, []).append(c.id)
        parts.append(Text("hosts: " + "; ".join(f"{h}: {', '.join(ids)}" for h, ids in hosts.items())))
    restarted = [c for c in snap.components if c.restarts or c.crashes]
    if restarted:
        parts.append(Text("; ".join(f"{c.id}: {len(c.crashes)} crash(es), {c.restarts} restart(s)"
                                    for c in restarted), style="yellow"))
    if failures:
        parts.append(Text("failed: " + "; ".join(failures), style="bold red"))
    else:
        parts.append(Text("every component ran and stopped cleanly", style="green"))
    return Group(*parts)
