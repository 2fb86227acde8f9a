"""The Inspection servicer: WM listings, task counters and metrics for tools; the outcomes components report."""

from __future__ import annotations

from cast.core.access import Access
from cast.core.records import Identity
from cast.core.system import System
from cast.server.conversions import entry_to_pb
from cast.server.rpc import Authenticator, Context, Servicer, rpc
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import inspection_pb2_grpc as insp_grpc
from cast.wire.metrics import snapshot_to_pb

__all__ = ["InspectionServicer"]


class InspectionServicer(Servicer, insp_grpc.InspectionServicer):
    """Serves tool reads of one :class:`System` (the rules: :class:`cast.core.access.Access`)."""

    SERVICE = "cast.v1.Inspection"

    def __init__(self, system: System, auth: Authenticator) -> None:
        self._system = system
        self.auth = auth

    @rpc
    async def ListEntries(
        self, request: insp_pb2.ListEntriesRequest, context: Context, who: Identity
    ) -> insp_pb2.ListEntriesResponse:
        """Entries of one WM without values, oldest write first."""
        listing = Access(self._system, who).list_entries(request.subarchitecture, request.type, request.limit)
        entries = []
        for record in listing.entries:
            pb = entry_to_pb(record)
            pb.ClearField("value")  # the record has none (cast.core.access.Access.list_entries): no empty Any either
            entries.append(pb)
        return insp_pb2.ListEntriesResponse(
            entries=entries, revision=listing.revision, pending_writes=listing.pending_writes, bytes=listing.bytes,
            max_bytes=listing.max_bytes, shared_bytes=listing.shared_bytes,
        )

    @rpc
    async def TaskStatistics(
        self, request: insp_pb2.TaskStatisticsRequest, context: Context, who: Identity
    ) -> insp_pb2.TaskStatisticsResponse:
        """Decision counts per SA since the server started."""
        counted = Access(self._system, who).task_statistics(request.subarchitecture)
        return insp_pb2.TaskStatisticsResponse(subarchitectures=[
            insp_pb2.TaskCounters(subarchitecture=sa, policy=policy, **counts) for sa, policy, counts in counted])

    @rpc
    async def GetMetrics(
        self, request: insp_pb2.GetMetricsRequest, context: Context, who: Identity
    ) -> insp_pb2.GetMetricsResponse:
        """What this server counted since it started (cast.core.metrics)."""
        return snapshot_to_pb(self._system.metrics.snapshot())

    @rpc
    async def Report(self, request: insp_pb2.ReportRequest, context: Context, who: Identity) -> insp_pb2.ReportResponse:
        """Record an outcome the caller measured; who it is comes from its token, never from the request."""
        Access(self._system, who).report(request.name, request.value)
        return insp_pb2.ReportResponse()
