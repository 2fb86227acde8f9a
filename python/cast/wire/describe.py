"""A system's description on the wire (``cast.v1.SystemDescription``), both ways.

The server sends what :func:`cast.core.describe.describe` found; the orchestrator's status view
and the tools read it back into the same records, so a server in another process is shown as one
in the orchestrator's own.
"""

from __future__ import annotations

from cast.core.describe import COUNTERS, ComponentSummary, SubarchitectureSummary, SystemSummary
from cast.core.sessions import ComponentInfo, ComponentState
from cast.v1 import directory_pb2 as dir_pb2

__all__ = ["component_state", "component_to_pb", "summary_from_pb", "summary_to_pb"]


def component_to_pb(info: ComponentInfo) -> dir_pb2.ComponentInfo:
    """Wire form of a directory entry."""
    return dir_pb2.ComponentInfo(
        id=info.id,
        subarchitecture=info.subarchitecture,
        privileged=info.privileged,
        language=info.language,
        kind=info.kind,
        state=int(info.state),  # type: ignore[arg-type]
        session_id=info.session_id,
        pid=info.pid,
        host=info.host,
        sessions=info.sessions,
        library_version=info.library_version,
    )


def component_state(value: int) -> ComponentState | None:
    """Core state from a wire value (None for unspecified or unknown)."""
    try:
        return ComponentState(value)
    except ValueError:
        return None


def _sa_to_pb(sa: SubarchitectureSummary) -> dir_pb2.SubarchitectureInfo:
    if not sa.hosted:
        return dir_pb2.SubarchitectureInfo(name=sa.name, endpoint=sa.endpoint)
    pb = dir_pb2.SubarchitectureInfo(
        name=sa.name, endpoint=sa.endpoint, task_manager_policy=sa.policy, revision=sa.revision, entries=sa.entries,
        bytes=sa.bytes, max_bytes=sa.max_bytes, waiting_tasks=sa.waiting, adopted_tasks=sa.adopted,
        type_counts=sa.types,
    )
    for name in COUNTERS:
        setattr(pb, f"tasks_{name}", sa.counters.get(name, 0))
    return pb


def summary_to_pb(summary: SystemSummary, shared: dir_pb2.SharedMemoryInfo | None = None) -> dir_pb2.SystemDescription:
    """The wire description (``shared``: the shared memory the server offers on its host)."""
    components = []
    for c in summary.components:
        pb = component_to_pb(c.info)
        pb.entries, pb.bytes = c.entries, c.bytes
        components.append(pb)
    return dir_pb2.SystemDescription(
        name=summary.name, endpoint=summary.endpoint,
        subarchitectures=[_sa_to_pb(sa) for sa in summary.subarchitectures], components=components,
        shared_memory=shared,
    )


def summary_from_pb(pb: dir_pb2.SystemDescription) -> SystemSummary:
    """The records of a wire description (an SA with no policy was described by a server that does not host it)."""
    sas = [
        SubarchitectureSummary(
            name=sa.name, endpoint=sa.endpoint, hosted=bool(sa.task_manager_policy), policy=sa.task_manager_policy,
            revision=sa.revision, entries=sa.entries, bytes=sa.bytes, max_bytes=sa.max_bytes,
            waiting=sa.waiting_tasks, adopted=sa.adopted_tasks,
            counters={name: getattr(sa, f"tasks_{name}") for name in COUNTERS}, types=dict(sa.type_counts),
        )
        for sa in pb.subarchitectures
    ]
    components = [
        ComponentSummary(
            ComponentInfo(
                id=c.id, subarchitecture=c.subarchitecture, privileged=c.privileged, language=c.language, kind=c.kind,
                state=component_state(c.state) or ComponentState.EXPECTED, session_id=c.session_id, pid=c.pid,
                host=c.host, sessions=c.sessions, library_version=c.library_version,
            ),
            c.entries, c.bytes,
        )
        for c in pb.components
    ]
    return SystemSummary(pb.name, pb.endpoint, sas, components)
