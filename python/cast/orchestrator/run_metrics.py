"""``cast run``'s metrics: ``--metrics HOST:PORT`` (Prometheus) and the summary's ``metrics``.

The /metrics endpoint serves the merged metrics of the servers running in
this process, read at scrape time; the summary's ``metrics`` (``--summary-json``)
adds those of servers on other hosts, asked with ``Inspection.GetMetrics``.
Both are the JSON shape of ``cast stats --json`` (docs/experiments.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import grpc

from cast.core.metrics_view import merge_snapshots
from cast.orchestrator.servers import ServerGroup
from cast.server.prometheus import MetricsEndpoint, serve_metrics
from cast.v1 import inspection_pb2, inspection_pb2_grpc
from cast.wire.metrics import snapshot_from_pb

__all__ = ["RunMetrics"]


class RunMetrics:
    """The metrics of a running system's servers; serves /metrics if given an address."""

    def __init__(self, servers: ServerGroup, listen: str | None, notice: Callable[[str], None]) -> None:
        """Bind /metrics on ``listen`` (HOST:PORT; port 0 picks one) and say where, or serve nothing if None.

        Bound before the servers start, so that a taken port ends the run before anything started.
        """
        self._servers = servers
        self._endpoint: MetricsEndpoint | None = None
        if listen is not None:
            self._endpoint = serve_metrics(listen, self.local)
            notice(f"metrics on http://{self._endpoint.address}/metrics")

    def local(self) -> dict[str, Any]:
        """The merged metrics of the servers in this process (none before they start)."""
        return merge_snapshots([hosted.system.metrics.snapshot() for hosted in list(self._servers.servers)])

    async def snapshot(self) -> dict[str, Any]:
        """Every server's metrics merged, those on other hosts asked over the network (skipped if unreachable)."""
        snapshots = [hosted.system.metrics.snapshot() for hosted in self._servers.servers]
        for far in self._servers.remote:
            if not far.process.running:
                continue
            async with self._servers.remote_channel(far) as channel:
                try:
                    reply = await inspection_pb2_grpc.InspectionStub(channel).GetMetrics(
                        inspection_pb2.GetMetricsRequest(), metadata=self._servers.orchestrator_metadata(),
                        timeout=2.0)
                except grpc.RpcError:
                    continue
            snapshots.append(snapshot_from_pb(reply))
        return merge_snapshots(snapshots)

    def close(self) -> None:
        """Stop serving /metrics (nothing if it was not served)."""
        if self._endpoint is not None:
            self._endpoint.close()
            self._endpoint = None
