"""The Inspection servicer: WM listings, task counters and metrics for tools; the outcomes components report."""

from __future__ import annotations

from cast.core.access import Access
from cast.core.system import System
from cast.errors import InvalidArgumentError
from cast.server.conversions import entry_to_pb
from cast.server.metrics_wire import snapshot_to_pb
from cast.server.rpc import Authenticator, Context, rpc
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import inspection_pb2_grpc as insp_grpc

__all__ = ["InspectionServicer"]


class InspectionServicer(insp_grpc.InspectionServicer):
    """Serves tool reads of one :class:`System`."""

    def __init__(self, system: System, auth: Authenticator) -> None:
        self._system = system
        self._auth = auth

    @rpc
    async def ListEntries(self, request: insp_pb2.ListEntriesRequest, context: Context) -> insp_pb2.ListEntriesResponse:
        """Entries of one WM without values, oldest write first."""
        self._auth.identify_read(context)
        host = self._system.host
        if not request.subarchitecture:
            raise InvalidArgumentError("name the subarchitecture to list")
        revision = host.revision(request.subarchitecture)  # NOT_FOUND for an SA not hosted here
        records = host.all_entries(request.subarchitecture)
        if request.type:
            records = [r for r in records if r.type == request.type]
        if request.limit:
            records = records[-request.limit :]
        entries = []
        for record in records:
            pb = entry_to_pb(record)
            pb.ClearField("value")  # a listing never carries content (ODR locks stay honoured)
            entries.append(pb)
        sa = request.subarchitecture
        return insp_pb2.ListEntriesResponse(
            entries=entries, revision=revision, pending_writes=host.pending_writes(sa), bytes=host.total_bytes(sa),
            max_bytes=host.limits.max_total_bytes, shared_bytes=host.shared_bytes(sa),
        )

    @rpc
    async def TaskStatistics(
        self, request: insp_pb2.TaskStatisticsRequest, context: Context
    ) -> insp_pb2.TaskStatisticsResponse:
        """Decision counts per SA since the server started."""
        self._auth.identify_read(context)
        tasks = self._system.tasks
        sas = [request.subarchitecture] if request.subarchitecture else self._system.host.subarchitectures
        out = []
        for sa in sas:
            policy = tasks.policy(sa).describe()  # NOT_FOUND for an SA not hosted here
            counts = tasks.counters[sa]
            out.append(insp_pb2.TaskCounters(subarchitecture=sa, policy=policy, **counts))
        return insp_pb2.TaskStatisticsResponse(subarchitectures=out)

    @rpc
    async def GetMetrics(self, request: insp_pb2.GetMetricsRequest, context: Context) -> insp_pb2.GetMetricsResponse:
        """What this server counted since it started (cast.core.metrics)."""
        self._auth.identify_read(context)
        return snapshot_to_pb(self._system.metrics.snapshot())

    @rpc
    async def Report(self, request: insp_pb2.ReportRequest, context: Context) -> insp_pb2.ReportResponse:
        """Record an outcome the caller measured; who it is comes from its token, never from the request."""
        Access(self._system, self._auth.identify(context)).report(request.name, request.value)
        return insp_pb2.ReportResponse()
