"""M9's load generator: many component sessions in one process, on grpc.aio (bench/many_components.py).

`python -m bench.session_load ENDPOINT SA TOKENS_FILE` opens one session per
(component id, token) pair of the JSON file, each as a component would: its
own channel, ``Directory.Register``, a ``Directory.Heartbeat`` stream beating
every lease_ms / 3, and one ``WorkingMemory.Watch`` of the SA's BytesValue
entries. The protocol on stdin/stdout, one line each:

- prints ``loaded`` once imported; on ``go`` opens every session at once and
  prints ``ready`` when all are registered and their watches created;
- on ``stop SENT_FILE`` (JSON {revision: ns}, the writer's stamps) waits (at
  most 20 s) until every session has every event, then prints
  {"samples_us": [...], "lost": [per session], "received": N}: every
  write -> event latency of every session (CLOCK_MONOTONIC stamps, taken when
  the event's message arrived), then closes everything and exits.
"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import sys
import time
from collections.abc import AsyncIterator
from typing import Any

import grpc

from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import entry_pb2
from cast.v1 import working_memory_pb2 as wm_pb2

VALUE_TYPE = "google.protobuf.BytesValue"


class Session:
    """One component's session and watch; the arrival stamps of its events."""

    def __init__(self, endpoint: str, sa: str, token: str) -> None:
        self.sa = sa
        self.metadata = (("authorization", f"Bearer {token}"),)
        self.channel = grpc.aio.insecure_channel(endpoint)
        self.stamps: dict[int, int] = {}
        self.raw: list[tuple[int, bytes]] = []  # (arrival ns, WatchResponse bytes), parsed at the end
        self.tasks: list[asyncio.Task[None]] = []
        self.closing = asyncio.Event()

    async def open(self) -> None:
        """Register, start beating, create the watch; returns once the watch is confirmed."""
        reply = await dir_grpc.DirectoryStub(self.channel).Register(
            dir_pb2.RegisterRequest(language="python", kind="unmanaged", pid=os.getpid(), host=socket.gethostname()),
            metadata=self.metadata,
        )
        beats = dir_grpc.DirectoryStub(self.channel).Heartbeat(
            self._beats(reply.session_id, reply.lease_ms), metadata=self.metadata
        )
        self.tasks.append(asyncio.create_task(self._drain(beats)))
        created = asyncio.get_running_loop().create_future()
        # Responses as bytes: parsing waits until the end, so the generator spends less per event.
        watch = self.channel.stream_stream(
            "/cast.v1.WorkingMemory/Watch", request_serializer=wm_pb2.WatchRequest.SerializeToString,
            response_deserializer=None,
        )(self._watch_requests(), metadata=self.metadata)
        self.tasks.append(asyncio.create_task(self._events(watch, created)))
        await created

    async def _beats(self, session_id: str, lease_ms: int) -> AsyncIterator[dir_pb2.HeartbeatRequest]:
        while True:
            yield dir_pb2.HeartbeatRequest(session_id=session_id, state=dir_pb2.COMPONENT_STATE_RUNNING)
            try:
                await asyncio.wait_for(self.closing.wait(), lease_ms / 3000)
                return
            except TimeoutError:
                pass

    async def _watch_requests(self) -> AsyncIterator[wm_pb2.WatchRequest]:
        yield wm_pb2.WatchRequest(
            create=wm_pb2.WatchCreate(
                watch_id=1, filters=[entry_pb2.ChangeFilter(subarchitecture=self.sa, type=VALUE_TYPE)]
            )
        )
        await self.closing.wait()

    async def _drain(self, call: Any) -> None:
        async for _ in call:
            pass

    async def _events(self, call: Any, created: asyncio.Future[None]) -> None:
        append = self.raw.append
        async for raw in call:
            t = time.perf_counter_ns()
            if created.done():
                append((t, raw))
                continue
            response = wm_pb2.WatchResponse.FromString(raw)
            if response.HasField("created"):
                created.set_result(None)
            elif response.HasField("failed"):
                created.set_exception(RuntimeError(f"watch refused: {response.failed.message}"))

    def parse(self) -> None:
        """The arrival stamp of every event received so far, by revision."""
        for t, raw in self.raw:
            for event in wm_pb2.WatchResponse.FromString(raw).events:
                self.stamps[event.revision] = t
        self.raw.clear()

    async def close(self) -> None:
        """End the streams (the session ends with its heartbeat stream) and the channel."""
        self.closing.set()
        await self.channel.close(None)
        for task in self.tasks:
            task.cancel()


async def _main(endpoint: str, sa: str, tokens: dict[str, str]) -> None:
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    print("loaded", flush=True)
    assert (await reader.readline()).strip() == b"go"
    sessions = [Session(endpoint, sa, token) for token in tokens.values()]
    await asyncio.gather(*(s.open() for s in sessions))
    print("ready", flush=True)
    words = (await reader.readline()).decode().split()
    assert words[0] == "stop", words
    with open(words[1]) as f:
        sent = {int(k): int(v) for k, v in json.load(f).items()}
    deadline = time.monotonic() + 20  # events still on their way: wait for them, not for ever
    while True:
        for s in sessions:
            s.parse()
        if time.monotonic() > deadline or all(r in s.stamps for s in sessions for r in sent):
            break
        await asyncio.sleep(0.05)
    samples: list[int] = []
    lost = []
    for s in sessions:
        got = [(s.stamps[r] - t0) // 1000 for r, t0 in sent.items() if r in s.stamps]
        samples += got
        lost.append(len(sent) - len(got))
    print(json.dumps({"samples_us": samples, "lost": lost, "received": len(samples)}), flush=True)
    await asyncio.gather(*(s.close() for s in sessions), return_exceptions=True)


if __name__ == "__main__":
    with open(sys.argv[3]) as tokens_file:
        pairs = json.load(tokens_file)
    asyncio.run(_main(sys.argv[1], sys.argv[2], pairs))
