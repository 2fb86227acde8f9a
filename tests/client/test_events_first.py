"""A write that wakes watch streams has its events sent before its reply (cast.server.write_stream).

One client connection carries a Watch and a Write stream, so what the server
sent first arrives first (nearly always: see the assertion): for a write, the
watcher's event comes before the writer's acknowledgement.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import grpc
from cast_testing_pb2 import Pose

from cast.core.records import Identity
from cast.server.wire import wire_system
from cast.v1 import entry_pb2
from cast.v1 import working_memory_pb2 as wm_pb2
from cast.v1 import working_memory_pb2_grpc as wm_grpc
from tests.client.conftest import ThreadServer

WRITES = 20


async def _arrivals(endpoint: str, token: str) -> list[tuple[str, int]]:
    """What arrived on the two streams, in order: ("event", revision) and ("reply", revision)."""
    metadata = (("authorization", f"Bearer {token}"),)
    arrived: list[tuple[str, int]] = []
    async with grpc.aio.insecure_channel(endpoint) as channel:
        stub = wm_grpc.WorkingMemoryStub(channel)
        watch_requests: asyncio.Queue[wm_pb2.WatchRequest] = asyncio.Queue()
        write_requests: asyncio.Queue[wm_pb2.WriteRequests] = asyncio.Queue()

        async def drain(queue: asyncio.Queue[Any]) -> AsyncIterator[Any]:
            while True:
                yield await queue.get()

        create = wm_pb2.WatchRequest()
        create.create.watch_id = 1
        create.create.filters.append(entry_pb2.ChangeFilter(subarchitecture="vision"))
        await watch_requests.put(create)
        watch = stub.Watch(drain(watch_requests), metadata=metadata)
        write = stub.Write(drain(write_requests), metadata=metadata)
        created: Any = await watch.read()
        assert created.HasField("created")

        async def events() -> None:
            while len([a for a in arrived if a[0] == "event"]) < WRITES:
                response: Any = await watch.read()
                arrived.extend(("event", e.revision) for e in response.events)

        async def replies() -> None:
            for i in range(WRITES):
                request = wm_pb2.WriteRequests()
                add = request.requests.add(id=i + 1).add
                add.address.id, add.address.subarchitecture = f"e{i}", "vision"
                add.value.Pack(Pose(x=i))
                await write_requests.put(request)
                reply: Any = await write.read()
                arrived.append(("reply", reply.replies[0].write.revision))
                await asyncio.sleep(0.01)  # each write alone: its event and reply are the only traffic

        await asyncio.wait_for(asyncio.gather(events(), replies()), 30)
        watch.cancel()
        write.cancel()
    return arrived


def test_a_writes_events_are_sent_before_its_reply() -> None:
    system = wire_system("t", ["vision"])
    server = ThreadServer(system)
    try:
        assert server.running is not None
        token = server.signer.issue(Identity("w", "vision"))
        arrived = asyncio.run(_arrivals(server.running.endpoint, token))
    finally:
        server.stop()
    order = {(kind, revision): i for i, (kind, revision) in enumerate(arrived)}
    revisions = [revision for kind, revision in arrived if kind == "reply"]
    assert len(revisions) == WRITES
    late = [r for r in revisions if order[("event", r)] > order[("reply", r)]]
    # Now and then the transport puts an event and a reply sent at the same moment into one write in
    # the other order: a few may come first; sent first, every reply does (all 20 without the rule).
    assert len(late) <= WRITES // 4, f"replies that came before their write's event: revisions {late} of {arrived}"
