"""Every RPC of the wire API, called with raw bytes: what any client (or an attacker) can send."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import grpc
from google.protobuf.descriptor import Descriptor

from cast.v1 import directory_pb2, inspection_pb2, task_manager_pb2, working_memory_pb2


@dataclass(frozen=True)
class Method:
    """One RPC: its path, its shape, and its request type."""

    path: str
    client_streaming: bool
    server_streaming: bool
    request: Descriptor

    @property
    def name(self) -> str:
        return self.path.rsplit("/", 1)[1]


def methods() -> list[Method]:
    """Every method of every CAST service."""
    out = []
    for module, service in ((working_memory_pb2, "WorkingMemory"), (task_manager_pb2, "TaskManager"),
                            (directory_pb2, "Directory"), (inspection_pb2, "Inspection")):
        svc = module.DESCRIPTOR.services_by_name[service]
        for m in svc.methods:
            out.append(Method(f"/{svc.full_name}/{m.name}", m.client_streaming, m.server_streaming, m.input_type))
    return out


def call(
    channel: grpc.Channel, method: Method, payloads: Sequence[bytes], metadata: Any = (), timeout: float = 3.0
) -> tuple[grpc.StatusCode, str, int]:
    """Send raw request bytes (one per message; a unary call uses the first); return (status, details, replies)."""
    replies = 0
    try:
        if not method.client_streaming and not method.server_streaming:
            fn: Any = channel.unary_unary(method.path)
            fn(payloads[0] if payloads else b"", metadata=metadata, timeout=timeout)
            return grpc.StatusCode.OK, "", 1
        if not method.client_streaming:
            fn = channel.unary_stream(method.path)
            stream = fn(payloads[0] if payloads else b"", metadata=metadata, timeout=timeout)
        else:
            fn = channel.stream_stream(method.path) if method.server_streaming else channel.stream_unary(method.path)

            def requests() -> Iterator[bytes]:
                yield from payloads

            stream = fn(requests(), metadata=metadata, timeout=timeout)
            if not method.server_streaming:
                return grpc.StatusCode.OK, "", 1
        for _ in stream:
            replies += 1
        return grpc.StatusCode.OK, "", replies
    except grpc.RpcError as exc:
        return exc.code(), exc.details() or "", replies
