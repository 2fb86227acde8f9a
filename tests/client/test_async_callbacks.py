"""An async write's done-callback may itself write and wait: on the session's socket and on the gRPC stream."""

from __future__ import annotations

import threading
from concurrent.futures import Future
from pathlib import Path

import pytest
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from tests.conftest import start_server


@pytest.mark.parametrize("shared_memory", ["on", "off"])
def test_a_done_callback_that_writes_and_waits_gets_its_answer(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, shared_memory: str) -> None:
    if shared_memory == "off":
        monkeypatch.setenv("CAST_SHARED_MEMORY", "off")
    server = start_server(tmp_path, {"system": "t", "subarchitectures": {"vision": {}}})
    writer = cast.UnmanagedComponent()
    # A short call timeout: a callback's write that nobody answered would fail with DeadlineExceededError.
    writer._cast_bind(GrpcTransport(server.endpoint, server.token("w", "vision"), Identity("w", "vision"),
                                    call_timeout=3.0))
    try:
        writer.add("e", BytesValue(value=b"0"))
        outcome: Future[object] = Future()

        def then(first: Future[cast.WriteResult]) -> None:
            try:
                outcome.set_result((first.result().version, writer.overwrite("e", BytesValue(value=b"2")).version,
                                    threading.current_thread().name))
            except BaseException as exc:  # the test looks at it
                outcome.set_exception(exc)

        writer.overwrite_async("e", BytesValue(value=b"1")).add_done_callback(then)
        first, second, thread = outcome.result(60)
        assert second > first, thread
        writer.overwrite("e", BytesValue(value=b"3"))  # the way for writes is whole after it
        assert writer.get("e", BytesValue).value == b"3"
    finally:
        writer._cast_close()
        server.stop()
