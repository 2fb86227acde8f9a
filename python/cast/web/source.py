"""The web view's side of the system: every call it makes to the servers, over gRPC, under one reader identity.

The directory names the SAs and the server hosting each; every other call goes
to the server of the SA it is about, as ``cast ls`` / ``cast stats`` do. The
calls are the public API only (``Directory``, ``Inspection``,
``TaskManager.ListTasks``, ``WorkingMemory.Get``): the view sees what any tool
with the system's credentials sees, and writes nothing.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, TypeVar

import grpc

from cast.bridges.status import STATUS_TYPE, statuses_of
from cast.client.channel import ServerLink, map_rpc_error
from cast.client.credentials import ClientTls, TokenSource
from cast.core.metrics_view import merge_snapshots
from cast.errors import CastError, NotFoundError
from cast.v1 import bridge_pb2, entry_pb2
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.wire.metrics import snapshot_from_pb

__all__ = ["SystemSource"]

R = TypeVar("R")


class SystemSource:
    """A running system reached through its directory at ``endpoint``; the named CastError if it does not answer.

    Thread-safe: the view's poller, its watch streams and the web server's
    request threads call it at once (gRPC channels are).
    """

    def __init__(self, endpoint: str, tokens: TokenSource, tls: ClientTls | None = None,
                 timeout: float = 10.0) -> None:
        self.endpoint = endpoint
        self.tokens = tokens
        self.tls = tls
        self._timeout = timeout
        self._mutex = threading.Lock()
        self._directory = ServerLink(endpoint, tls)
        self._links: dict[str, ServerLink] = {endpoint: self._directory}
        try:
            self.system = self._call(self._directory.directory.DescribeSystem, dir_pb2.DescribeSystemRequest())
        except CastError:
            self._directory.close()
            raise

    def _call(self, method: Callable[..., R], request: Any, token: str | None = None) -> R:
        metadata = (("authorization", f"Bearer {token}"),) if token is not None else self.tokens.metadata()
        try:
            return method(request, metadata=metadata, timeout=self._timeout)
        except grpc.RpcError as exc:
            raise map_rpc_error(exc) from None

    # ------------------------------------------------------------ servers

    @property
    def name(self) -> str:
        """The system's name."""
        return str(self.system.name)

    @property
    def subarchitectures(self) -> list[str]:
        """Every SA, in the directory's (the configuration's) order."""
        return [sa.name for sa in self.system.subarchitectures]

    def link(self, sa: str) -> ServerLink:
        """The link to the server hosting ``sa``; NotFoundError naming the known SAs."""
        for info in self.system.subarchitectures:
            if info.name == sa:
                if not info.endpoint or info.endpoint == self.system.endpoint:
                    return self._directory
                with self._mutex:
                    link = self._links.get(info.endpoint)
                    if link is None:
                        link = self._links[info.endpoint] = ServerLink(info.endpoint, self.tls)
                return link
        raise NotFoundError(f"no subarchitecture '{sa}' in system '{self.name}' (known: "
                            f"{', '.join(self.subarchitectures)})")

    def servers(self) -> list[tuple[ServerLink, list[str]]]:
        """Each server with the SAs it hosts, the directory's first."""
        out: dict[str, tuple[ServerLink, list[str]]] = {}
        for sa in self.subarchitectures:
            link = self.link(sa)
            out.setdefault(link.endpoint, (link, []))[1].append(sa)
        return list(out.values())

    # --------------------------------------------------------------- reads

    def describe(self) -> tuple[list[dir_pb2.SubarchitectureInfo], list[dir_pb2.ComponentInfo]]:
        """Every SA as its own server describes it now (revision, entries), and the directory's components."""
        sas: dict[str, dir_pb2.SubarchitectureInfo] = {}
        components: list[dir_pb2.ComponentInfo] = []
        for link, hosted in self.servers():
            desc = self._call(link.directory.DescribeSystem, dir_pb2.DescribeSystemRequest())
            sas.update((info.name, info) for info in desc.subarchitectures if info.name in hosted)
            if link is self._directory:
                self.system = desc
                components = list(desc.components)
        return [sas[name] for name in self.subarchitectures if name in sas], components

    def metrics(self) -> dict[str, Any]:
        """What every server counted, merged (the shape of ``cast stats --json``)."""
        return merge_snapshots([snapshot_from_pb(self._call(link.inspection.GetMetrics, insp_pb2.GetMetricsRequest()))
                                for link, _ in self.servers()])

    def task_counters(self) -> list[insp_pb2.TaskCounters]:
        """Each SA's task manager: policy and decision counts, in the directory's order."""
        found: dict[str, insp_pb2.TaskCounters] = {}
        for link, _ in self.servers():
            stats = self._call(link.inspection.TaskStatistics, insp_pb2.TaskStatisticsRequest())
            found.update((c.subarchitecture, c) for c in stats.subarchitectures)
        return [found[sa] for sa in self.subarchitectures if sa in found]

    def tasks(self) -> list[tm_pb2.Task]:
        """The live tasks (waiting and adopted) of every SA."""
        out: list[tm_pb2.Task] = []
        for link, _ in self.servers():
            out.extend(self._call(link.tm.ListTasks, tm_pb2.ListTasksRequest()).tasks)
        return out

    def bridge_statuses(self) -> list[bridge_pb2.BridgeStatus]:
        """The status entry of every bridge (``cast.v1.BridgeStatus``, in any SA: docs/ros.md)."""
        entries: list[entry_pb2.Entry] = []
        for link, hosted in self.servers():
            for sa in hosted:
                # Listing counts as no read in the metrics the page shows: only a WM with a status is read.
                if self.entries(sa, STATUS_TYPE).entries:
                    request = wm_pb2.GetByTypeRequest(subarchitecture=sa, type=STATUS_TYPE)
                    entries.extend(self._call(link.wm.GetByType, request).entries)
        return statuses_of(entries)

    def entries(self, sa: str, type_name: str = "", limit: int = 0) -> insp_pb2.ListEntriesResponse:
        """The entries of one WM without values (the most recent ``limit``, oldest first; 0: all)."""
        request = insp_pb2.ListEntriesRequest(subarchitecture=sa, type=type_name, limit=limit)
        return self._call(self.link(sa).inspection.ListEntries, request)

    def get(self, sa: str, entry_id: str) -> entry_pb2.Entry:
        """One entry with its value; NotFoundError when it is not there (any more)."""
        request = wm_pb2.GetRequest(address=entry_pb2.EntryAddress(id=entry_id, subarchitecture=sa))
        return self._call(self.link(sa).wm.Get, request).entry

    def schema(self, sa: str, type_name: str) -> dir_pb2.GetSchemaResponse:
        """The descriptors of a type as registered on the SA's server; NotFoundError if nobody registered it."""
        return self._call(self.link(sa).directory.GetSchema, dir_pb2.GetSchemaRequest(type=type_name))

    def accepts(self, token: str) -> bool:
        """Whether the system accepts ``token`` (signed with its secret, not expired): the directory decides.

        Raises the named error when the directory cannot answer, so a server
        that is away is not taken for a bad token.
        """
        try:
            self._call(self._directory.directory.DescribeSystem, dir_pb2.DescribeSystemRequest(), token=token)
        except CastError as exc:
            if exc.code in ("UNAUTHENTICATED", "PERMISSION_DENIED"):
                return False
            raise
        return True

    def close(self) -> None:
        """Close every channel (streams on them end)."""
        with self._mutex:
            links = list(self._links.values())
        for link in links:
            link.close()
