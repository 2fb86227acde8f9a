"""What a server holds, described once: for the directory's answer, the orchestrator's status and the tools.

:func:`describe` reads one :class:`~cast.core.system.System` into plain records. The Directory
servicer translates them to a ``cast.v1.SystemDescription``; the orchestrator's status view reads
them of the servers in its own process, and of servers on other hosts from their
``DescribeSystem`` answer, translated back by the same wire code; ``cast ls`` and ``cast
components`` print them. So a figure means the same wherever it is shown.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from cast.core.sessions import ComponentInfo
from cast.core.system import System
from cast.core.tasks import TaskState

__all__ = ["COUNTERS", "ComponentSummary", "SubarchitectureSummary", "SystemSummary", "describe"]

COUNTERS = ("proposed", "adopted", "rejected", "retracted", "completed")
"""The task manager's decision counters, in this order everywhere they are shown."""


@dataclass(frozen=True)
class SubarchitectureSummary:
    """One SA as a server sees it: its WM and its task manager.

    Of an SA another server serves, only ``name`` and ``endpoint`` are known (``hosted`` is False).
    """

    name: str
    endpoint: str
    hosted: bool = True  # served by the server that described it (False: only where it is served is known)
    policy: str = ""
    revision: int = 0
    entries: int = 0
    bytes: int = 0
    max_bytes: int = 0
    waiting: int = 0  # live tasks now
    adopted: int = 0
    counters: Mapping[str, int] = field(default_factory=dict)  # decisions since the server started: COUNTERS
    types: Mapping[str, int] = field(default_factory=dict)  # entries per type


@dataclass(frozen=True)
class ComponentSummary:
    """One component the server knows, with what it holds there (the entries it wrote last, their bytes)."""

    info: ComponentInfo
    entries: int = 0
    bytes: int = 0


@dataclass(frozen=True)
class SystemSummary:
    """One server's view of the system."""

    name: str
    endpoint: str  # the directory's address
    subarchitectures: list[SubarchitectureSummary]
    components: list[ComponentSummary]


def describe(system: System, endpoint: str, served: Mapping[str, str],
             elsewhere: Mapping[str, str] | None = None) -> SystemSummary:
    """``system`` now: its SAs and the components its sessions know.

    ``served``: where each of its SAs is served; ``elsewhere``: the SAs other servers serve, and where.
    """
    host, tasks = system.host, system.tasks
    revisions = host.revisions()
    live = tasks.tasks()
    sas = [
        SubarchitectureSummary(
            name=sa, endpoint=served.get(sa, ""), policy=tasks.policy(sa).describe(), revision=revisions[sa],
            entries=host.entry_count(sa), bytes=host.total_bytes(sa), max_bytes=host.limits.max_total_bytes,
            waiting=sum(1 for t in live if t.subarchitecture == sa and t.state is TaskState.WAITING),
            adopted=sum(1 for t in live if t.subarchitecture == sa and t.state is TaskState.ADOPTED),
            counters={k: tasks.counters[sa][k] for k in COUNTERS}, types=host.type_counts(sa),
        )
        for sa in host.subarchitectures
    ]
    sas += [SubarchitectureSummary(name=sa, endpoint=ep, hosted=False) for sa, ep in (elsewhere or {}).items()]
    usage = host.usage()
    components = [ComponentSummary(info, *usage.get(info.id, (0, 0))) for info in system.sessions.components()]
    return SystemSummary(system.name, endpoint, sas, components)
