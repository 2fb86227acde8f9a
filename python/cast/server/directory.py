"""The Directory servicer: system description, sessions, schemas."""

from __future__ import annotations

from collections.abc import AsyncIterator

from google.protobuf import descriptor_pb2

from cast.core.access import Access, run_async
from cast.core.system import System
from cast.errors import InvalidArgumentError
from cast.server.conversions import component_state, component_to_pb
from cast.server.routes import Routes
from cast.server.rpc import Authenticator, Context, rpc, stream_rpc
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc

__all__ = ["DirectoryServicer", "describe"]


def describe(
    system: System, routes: Routes, shared: dir_pb2.SharedMemoryInfo | None = None
) -> dir_pb2.SystemDescription:
    """The wire description of a system, with where each of its SAs is served and its shared memory offered."""
    revisions = system.host.revisions()
    usage = system.host.usage()
    components = []
    for info in system.sessions.components():
        pb = component_to_pb(info)
        pb.entries, pb.bytes = usage.get(info.id, (0, 0))
        components.append(pb)
    return dir_pb2.SystemDescription(
        name=system.name,
        subarchitectures=[
            dir_pb2.SubarchitectureInfo(
                name=sa,
                endpoint=routes.local.get(sa, ""),
                task_manager_policy=system.tasks.policy(sa).describe(),
                revision=revisions[sa],
                entries=system.host.entry_count(sa),
                bytes=system.host.total_bytes(sa),
                max_bytes=system.host.limits.max_total_bytes,
            )
            for sa in system.host.subarchitectures
        ]
        + [dir_pb2.SubarchitectureInfo(name=sa, endpoint=ep) for sa, ep in routes.remote.items()],
        components=components,
        endpoint=routes.endpoint,
        shared_memory=shared,
    )


class DirectoryServicer(dir_grpc.DirectoryServicer):
    """Serves the directory of one :class:`System`."""

    def __init__(
        self, system: System, auth: Authenticator, routes: Routes, shared: dir_pb2.SharedMemoryInfo | None = None
    ) -> None:
        self._system = system
        self._auth = auth
        self._routes = routes
        self._shared = shared  # where this server offers its shared memory (cast.server.shared_socket)

    @rpc
    async def DescribeSystem(
        self, request: dir_pb2.DescribeSystemRequest, context: Context
    ) -> dir_pb2.SystemDescription:
        """Describe SAs, endpoints and components."""
        self._auth.identify_read(context)
        return describe(self._system, self._routes, self._shared)

    @rpc
    async def Register(
        self, request: dir_pb2.RegisterRequest, context: Context
    ) -> dir_pb2.RegisterResponse:
        """Start a session for the caller."""
        who = self._auth.identify(context)
        sessions = self._system.sessions
        session_id = sessions.register(
            who, request.language, request.kind, request.pid, request.host, request.library_version
        )
        return dir_pb2.RegisterResponse(
            session_id=session_id, lease_ms=sessions.lease_ms,
            system=describe(self._system, self._routes, self._shared),
            component_id=who.component_id, subarchitecture=who.subarchitecture, privileged=who.privileged,
        )

    @stream_rpc
    async def Heartbeat(
        self, request_iterator: AsyncIterator[dir_pb2.HeartbeatRequest], context: Context
    ) -> AsyncIterator[dir_pb2.HeartbeatResponse]:
        """Keep a session alive; the session ends with this stream."""
        who = self._auth.identify(context)
        sessions = self._system.sessions
        session_id = ""
        try:
            async for beat in request_iterator:
                if session_id and beat.session_id != session_id:
                    raise InvalidArgumentError("one heartbeat stream serves one session")
                # Checked before the stream adopts the session: a stream that names another
                # component's session must not end that session when it is refused.
                sessions.heartbeat(who, beat.session_id, component_state(beat.state))
                session_id = beat.session_id
                yield dir_pb2.HeartbeatResponse(lease_ms=sessions.lease_ms)
        finally:
            # The component is gone (or its stream broke): release what it held.
            if session_id:
                sessions.end(session_id)

    @rpc
    async def AwaitRun(self, request: dir_pb2.AwaitRunRequest, context: Context) -> dir_pb2.AwaitRunResponse:
        """Return once the start barrier is released (at once if there is none)."""
        self._auth.identify(context)
        await self._system.barrier.wait_async()
        return dir_pb2.AwaitRunResponse()

    @rpc
    async def RegisterSchemas(
        self, request: dir_pb2.RegisterSchemasRequest, context: Context
    ) -> dir_pb2.RegisterSchemasResponse:
        """Store entry type descriptors."""
        access = Access(self._system, self._auth.identify(context))
        types = await run_async(self._system, access.register_schemas(list(request.files.file)))
        return dir_pb2.RegisterSchemasResponse(types=types)

    @rpc
    async def GetSchema(
        self, request: dir_pb2.GetSchemaRequest, context: Context
    ) -> dir_pb2.GetSchemaResponse:
        """Descriptors of one type."""
        self._auth.identify_read(context)
        files = self._system.schemas.files_for(request.type)
        return dir_pb2.GetSchemaResponse(files=descriptor_pb2.FileDescriptorSet(file=files))
