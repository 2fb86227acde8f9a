"""Server reflection, v1 and v1alpha, that also knows the registered entry types.

grpcio-reflection serves only ``grpc.reflection.v1alpha``; generic tools
(grpcurl, Postman) ask for ``grpc.reflection.v1`` first. The two protocols
are the same messages in two packages, so the v1 method is served by the same
servicer with the v1alpha message classes, which read and write identical
bytes. Symbols are looked up first in the server's schema registry (the
system's files, the well-known types and every registered entry type, so a
tool can decode an entry's ``Any`` value) and then in the process's default
pool (health, reflection itself).
"""

from __future__ import annotations

from typing import Any

import grpc
from google.protobuf import descriptor_pool
from google.protobuf.descriptor import Descriptor, FieldDescriptor, FileDescriptor
from grpc_reflection.v1alpha import reflection, reflection_pb2

from cast.core.schemas import SchemaRegistry

__all__ = ["V1_SERVICE_NAME", "add_reflection"]

V1_SERVICE_NAME = "grpc.reflection.v1.ServerReflection"


class _Pools:
    """The lookups the reflection servicer makes, tried in the registry's pool, then in the default one."""

    def __init__(self, schemas: SchemaRegistry) -> None:
        self._pools = (schemas.pool, descriptor_pool.Default())

    def _first(self, method: str, *args: Any) -> Any:
        error: KeyError | None = None
        for pool in self._pools:
            try:
                return getattr(pool, method)(*args)
            except KeyError as exc:
                error = exc
        assert error is not None
        raise error

    def FindFileByName(self, name: str) -> FileDescriptor:
        """The file of that name."""
        return self._first("FindFileByName", name)  # type: ignore[no-any-return]

    def FindFileContainingSymbol(self, symbol: str) -> FileDescriptor:
        """The file defining a message, enum, service or method."""
        return self._first("FindFileContainingSymbol", symbol)  # type: ignore[no-any-return]

    def FindMessageTypeByName(self, name: str) -> Descriptor:
        """A message type."""
        return self._first("FindMessageTypeByName", name)  # type: ignore[no-any-return]

    def FindExtensionByNumber(self, message: Descriptor, number: int) -> FieldDescriptor:
        """An extension of ``message``, in the pool that defines ``message``."""
        return message.file.pool.FindExtensionByNumber(message, number)

    def FindAllExtensions(self, message: Descriptor) -> list[FieldDescriptor]:
        """Every extension of ``message``."""
        return list(message.file.pool.FindAllExtensions(message))


def add_reflection(registrar: Any, schemas: SchemaRegistry, service_names: tuple[str, ...]) -> None:
    """Serve reflection (v1 and v1alpha) for ``service_names`` and every registered type."""
    names = (*service_names, reflection.SERVICE_NAME, V1_SERVICE_NAME)
    servicer = reflection.aio.ReflectionServicer(names, pool=_Pools(schemas))  # type: ignore[attr-defined]
    for service in (reflection.SERVICE_NAME, V1_SERVICE_NAME):
        handler = grpc.stream_stream_rpc_method_handler(
            servicer.ServerReflectionInfo,
            request_deserializer=reflection_pb2.ServerReflectionRequest.FromString,
            response_serializer=reflection_pb2.ServerReflectionResponse.SerializeToString,
        )
        registrar.add_generic_rpc_handlers(
            (grpc.method_handlers_generic_handler(service, {"ServerReflectionInfo": handler}),)
        )
