"""The Directory servicer: system description, sessions, schemas (the rules: :class:`cast.core.access.Access`)."""

from __future__ import annotations

from collections.abc import AsyncIterator

from google.protobuf import descriptor_pb2

from cast.core.access import Access, run_async
from cast.core.records import Identity
from cast.core.system import System
from cast.server.routes import Routes
from cast.server.rpc import Authenticator, Context, Servicer, rpc, stream_rpc
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.wire.describe import component_state, summary_to_pb

__all__ = ["DirectoryServicer"]


class DirectoryServicer(Servicer, dir_grpc.DirectoryServicer):
    """Serves the directory of one :class:`System`."""

    SERVICE = "cast.v1.Directory"

    def __init__(
        self, system: System, auth: Authenticator, routes: Routes, shared: dir_pb2.SharedMemoryInfo | None = None
    ) -> None:
        self._system = system
        self.auth = auth
        self._routes = routes
        self._shared = shared  # where this server offers its shared memory (cast.server.shared_socket)

    def _describe(self, who: Identity) -> dir_pb2.SystemDescription:
        routes = self._routes
        summary = Access(self._system, who).describe(routes.endpoint, routes.local, routes.remote)
        return summary_to_pb(summary, self._shared)

    @rpc
    async def DescribeSystem(
        self, request: dir_pb2.DescribeSystemRequest, context: Context, who: Identity
    ) -> dir_pb2.SystemDescription:
        """Describe SAs, endpoints and components."""
        return self._describe(who)

    @rpc
    async def Register(
        self, request: dir_pb2.RegisterRequest, context: Context, who: Identity
    ) -> dir_pb2.RegisterResponse:
        """Start a session for the caller."""
        access = Access(self._system, who)
        session_id = access.register(request.language, request.kind, request.pid, request.host,
                                     request.library_version)
        return dir_pb2.RegisterResponse(
            session_id=session_id, lease_ms=self._system.sessions.lease_ms, system=self._describe(who),
            component_id=who.component_id, subarchitecture=who.subarchitecture, privileged=who.privileged,
        )

    @stream_rpc
    async def Heartbeat(
        self, request_iterator: AsyncIterator[dir_pb2.HeartbeatRequest], context: Context, who: Identity
    ) -> AsyncIterator[dir_pb2.HeartbeatResponse]:
        """Keep a session alive; the session ends with this stream (cast.core.sessions.SessionStream)."""
        stream = Access(self._system, who).session_stream()
        try:
            async for beat in request_iterator:
                lease_ms = stream.beat(beat.session_id, component_state(beat.state))
                yield dir_pb2.HeartbeatResponse(lease_ms=lease_ms)
        finally:
            stream.end()  # the component is gone (or its stream broke): release what it held

    @rpc
    async def AwaitRun(
        self, request: dir_pb2.AwaitRunRequest, context: Context, who: Identity
    ) -> dir_pb2.AwaitRunResponse:
        """Return once the start barrier is released (at once if there is none)."""
        await self._system.barrier.wait_async()
        return dir_pb2.AwaitRunResponse()

    @rpc
    async def RegisterSchemas(
        self, request: dir_pb2.RegisterSchemasRequest, context: Context, who: Identity
    ) -> dir_pb2.RegisterSchemasResponse:
        """Store entry type descriptors."""
        access = Access(self._system, who)
        types = await run_async(self._system, access.register_schemas(list(request.files.file)))
        return dir_pb2.RegisterSchemasResponse(types=types)

    @rpc
    async def GetSchema(
        self, request: dir_pb2.GetSchemaRequest, context: Context, who: Identity
    ) -> dir_pb2.GetSchemaResponse:
        """Descriptors of one type."""
        files = self._system.schemas.files_for(request.type)
        return dir_pb2.GetSchemaResponse(files=descriptor_pb2.FileDescriptorSet(file=files))
