"""The replies of a transport's writes: made when the transport takes them, in order, each with its result."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

import cast.server.writes as writes_module
from cast.core.records import Identity
from cast.server.wire import wire_system
from cast.server.writes import Writes
from cast.v1 import working_memory_pb2 as wm_pb2

WHO = Identity("w", "vision")


def _add(request_id: int, entry_id: str) -> wm_pb2.WriteRequest:
    request = wm_pb2.WriteRequest(id=request_id)
    request.add.address.id, request.add.address.subarchitecture = entry_id, "vision"
    request.add.value.type_url, request.add.value.value = "type.googleapis.com/t.X", b"x"
    return request


def _writes() -> Writes:
    return Writes(wire_system("t", ["vision"]), lambda: (WHO, 0.0), lambda: None)


def test_each_reply_carries_its_result_and_they_come_in_the_order_applied() -> None:
    async def run() -> list[wm_pb2.WriteReply]:
        writes = _writes()
        overwrite = wm_pb2.WriteRequest(id=3)
        overwrite.overwrite.address.id, overwrite.overwrite.address.subarchitecture = "a", "vision"
        overwrite.overwrite.value.type_url = "type.googleapis.com/t.X"
        get = wm_pb2.WriteRequest(id=4)
        get.get.address.id, get.get.address.subarchitecture = "a", "vision"
        writes.apply([_add(1, "a"), _add(2, "a"), overwrite, get])  # the second add fails: the entry exists
        assert writes.ready
        return list(writes.take().replies)

    first, failed, overwritten, got = asyncio.run(run())
    assert (first.id, first.write.revision) == (1, 1) and first.write.version > 0
    assert failed.id == 2 and failed.error.code == "ALREADY_EXISTS"
    assert (overwritten.id, overwritten.write.revision) == (3, 2)
    assert overwritten.write.version > first.write.version
    assert got.id == 4 and got.get.entry.version == overwritten.write.version


@pytest.mark.incompatible_with_mypyc
def test_an_answer_that_fails_when_its_reply_is_made_gives_that_request_an_internal_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def broken(reply: wm_pb2.WriteReply, result: Any) -> None:
        raise ValueError("an answer that does not fit its reply")

    monkeypatch.setattr(writes_module, "_write_answer", broken)

    async def run() -> list[wm_pb2.WriteReply]:
        writes = _writes()
        get = wm_pb2.WriteRequest(id=2)
        get.get.address.id, get.get.address.subarchitecture = "a", "vision"
        writes.apply([_add(1, "a"), get])
        return list(writes.take().replies)

    broke, got = asyncio.run(run())
    assert broke.id == 1 and broke.error.code == "INTERNAL" and "does not fit" in broke.error.message
    assert got.id == 2 and got.get.entry.value.value == b"x"  # applied all the same, and the next one answered
