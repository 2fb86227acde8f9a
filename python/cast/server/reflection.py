"""Server reflection, v1 and v1alpha, that also knows the registered entry types.

grpcio-reflection serves only ``grpc.reflection.v1alpha``; generic tools
(grpcurl, Postman) ask for ``grpc.reflection.v1`` first. The two protocols
are the same messages in two packages, so the v1 method is served by the same
servicer with the v1alpha message classes, which read and write identical
bytes. Symbols are looked up first in the server's schema registry (the
system's files, the well-known types and every registered entry type, so a
tool can decode an entry's ``Any`` value), then in the process's default
pool (health, reflection v1alpha), then in a pool of the v1 file, which
grpcio-reflection does not ship: made from the v1alpha file, renamed, so that
every service listed can be described (``grpcurl describe``).
"""

from __future__ import annotations

from typing import Any

import grpc
from google.protobuf import descriptor_pb2, descriptor_pool
from google.protobuf.descriptor import Descriptor, FieldDescriptor, FileDescriptor
from grpc_reflection.v1alpha import reflection, reflection_pb2

from cast.core.schemas import SchemaRegistry

__all__ = ["V1_SERVICE_NAME", "add_reflection"]

V1_SERVICE_NAME = "grpc.reflection.v1.ServerReflection"


_V1ALPHA = "grpc.reflection.v1alpha"
_V1 = "grpc.reflection.v1"


def _v1_pool() -> descriptor_pool.DescriptorPool:
    """A pool holding ``grpc/reflection/v1/reflection.proto``: the v1alpha file in the v1 package."""
    alpha = descriptor_pb2.FileDescriptorProto()
    reflection_pb2.DESCRIPTOR.CopyToProto(alpha)
    # Names appear as ".grpc.reflection.v1alpha.X" in field types and as the package: rename both.
    v1 = alpha
    v1.name = "grpc/reflection/v1/reflection.proto"
    v1.package = _V1
    for message in v1.message_type:
        for field in message.field:
            if field.HasField("type_name"):  # assigning even "" would mark a scalar field as typed
                field.type_name = field.type_name.replace(f".{_V1ALPHA}.", f".{_V1}.")
    for service in v1.service:
        for method in service.method:
            method.input_type = method.input_type.replace(f".{_V1ALPHA}.", f".{_V1}.")
            method.output_type = method.output_type.replace(f".{_V1ALPHA}.", f".{_V1}.")
    pool = descriptor_pool.DescriptorPool()
    pool.Add(v1)
    return pool


class _Pools:
    """The lookups the reflection servicer makes, tried in the registry's pool, the default one, then v1's."""

    def __init__(self, schemas: SchemaRegistry) -> None:
        self._pools = (schemas.pool, descriptor_pool.Default(), _v1_pool())

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
        try:
            return self._first("FindFileContainingSymbol", symbol)  # type: ignore[no-any-return]
        except KeyError:
            # protobuf's pools find no method by name (grpcurl describe Service.Method): its service's file.
            service, _, method = symbol.rpartition(".")
            if not service:
                raise
            for pool in self._pools:
                try:
                    found = pool.FindServiceByName(service)
                except KeyError:
                    continue
                if method in found.methods_by_name:
                    return found.file
            raise

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
