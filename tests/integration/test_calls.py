"""One table says which credential each call needs (cast.core.calls), and that table is what the server does.

The table must name every call of every ``cast.v1`` service, and nothing else; a server whose reads
are open (``auth.reads_require_token: false``) must then answer every READ call without a token and
refuse every TOKEN call without one, UNAUTHENTICATED, before it looks at the request.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import grpc
import pytest
from google.protobuf import message_factory

from cast.core.calls import CALLS, Credential
from cast.v1 import agent_pb2, directory_pb2, inspection_pb2, task_manager_pb2, working_memory_pb2
from tests.conftest import ServerHandle, start_server

SERVED = ("cast.v1.WorkingMemory", "cast.v1.TaskManager", "cast.v1.Directory", "cast.v1.Inspection")


def _methods() -> Iterator[Any]:
    for module in (agent_pb2, directory_pb2, inspection_pb2, task_manager_pb2, working_memory_pb2):
        for service in module.DESCRIPTOR.services_by_name.values():
            yield from service.methods


def _call(channel: grpc.Channel, method: Any) -> Callable[..., Any]:
    """A generic callable for ``method`` of the right shape (empty requests, no token)."""
    name = f"/{method.containing_service.full_name}/{method.name}"
    request = message_factory.GetMessageClass(method.input_type)
    response = message_factory.GetMessageClass(method.output_type)
    kind = {(False, False): channel.unary_unary, (False, True): channel.unary_stream,
            (True, False): channel.stream_unary, (True, True): channel.stream_stream}[
        (method.client_streaming, method.server_streaming)]
    fn = kind(name, request_serializer=request.SerializeToString, response_deserializer=response.FromString)
    if method.client_streaming:
        return lambda: fn(iter([request()]), timeout=5)
    return lambda: fn(request(), timeout=5)


def test_the_table_names_every_call_of_every_service_and_nothing_else() -> None:
    calls = {f"{m.containing_service.full_name}/{m.name}" for m in _methods()}
    assert calls - CALLS.keys() == set(), "calls with no credential in cast.core.calls.CALLS"
    assert CALLS.keys() - calls == set(), "credentials of calls no service has"


@pytest.fixture(scope="module")
def open_reads(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerHandle]:
    """A server whose reads need no token."""
    handle = start_server(tmp_path_factory.mktemp("open"), {
        "system": "open", "subarchitectures": {"vision": {}}, "auth": {"reads_require_token": False}})
    yield handle
    handle.stop()


@pytest.mark.parametrize("method", [m for m in _methods() if m.containing_service.full_name in SERVED],
                         ids=lambda m: f"{m.containing_service.name}.{m.name}")
def test_the_server_asks_each_call_for_the_credential_of_the_table(open_reads: ServerHandle, method: Any) -> None:
    server = open_reads
    needs = CALLS[f"{method.containing_service.full_name}/{method.name}"]
    with grpc.insecure_channel(server.endpoint) as channel:
        call = _call(channel, method)
        try:
            answer = call()
            if method.server_streaming:
                next(iter(answer), None)
            code = grpc.StatusCode.OK
        except grpc.RpcError as exc:
            code = exc.code()
    if needs is Credential.TOKEN:
        assert code == grpc.StatusCode.UNAUTHENTICATED, f"{method.name} without a token: {code}"
    else:
        assert needs is Credential.READ
        assert code != grpc.StatusCode.UNAUTHENTICATED, f"{method.name}, a read, refused without a token"
