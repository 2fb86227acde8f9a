"""One test body, two transports (remote over gRPC, in process without gRPC), two kinds of server.

Each body runs against a memory-only server and against one whose journal
writers wait for (``batch``), where a write becomes visible only once durable:
the rules a component sees must not depend on either choice.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from cast.auth import TokenSigner
from cast.client.component import Component
from cast.client.grpc_transport import GrpcTransport
from cast.client.local_transport import LocalTransport
from cast.core.journal import Journal
from cast.core.policies import make_policy
from cast.core.records import Identity, Limits
from cast.core.system import System
from cast.server.app import RunningServer, start_server
from cast.server.wire import wire_system

Factory = Callable[..., Any]


class ThreadServer:
    """A real gRPC server on port 0 running on an event loop in a background thread."""

    def __init__(self, system: System) -> None:
        self.system = system
        self.signer = TokenSigner(b"client-test-secret-0123456789abcdef")
        self.loop = asyncio.new_event_loop()
        started = threading.Event()
        self.running: RunningServer | None = None

        def body() -> None:
            asyncio.set_event_loop(self.loop)
            self.running = self.loop.run_until_complete(start_server(system, self.signer))
            started.set()
            self.loop.run_forever()

        self.thread = threading.Thread(target=body, daemon=True)
        self.thread.start()
        started.wait(10)

    def stop(self) -> None:
        assert self.running is not None
        asyncio.run_coroutine_threadsafe(self.running.stop(0), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


@pytest.fixture(params=["grpc", "in-process", "grpc-journal", "in-process-journal"])
def make_component(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Factory]:
    """``make_component(cls, id, sa, privileged=False)``: a bound component of class ``cls``."""
    journal = Journal(tmp_path / "wm.db", "batch", 64) if request.param.endswith("-journal") else None
    system = wire_system(
        "t",
        ["vision", "language"],
        policies={"vision": make_policy("fifo", {"max_concurrent": 1})},
        limits=Limits(history_events=64),
        journal=journal,
    )
    server = ThreadServer(system)
    made: list[Component] = []

    def make(cls: type[Component], component_id: str, sa: str = "vision", privileged: bool = False) -> Any:
        identity = Identity(component_id, sa, privileged)
        if request.param.startswith("grpc"):
            assert server.running is not None
            transport: Any = GrpcTransport(server.running.endpoint, server.signer.issue(identity), identity)
        else:
            transport = LocalTransport(system, identity)
        component = cls()
        component._cast_bind(transport)
        made.append(component)
        return component

    make.system = system  # type: ignore[attr-defined]
    make.mode = request.param  # type: ignore[attr-defined]
    make.endpoint = server.running.endpoint if server.running is not None else ""  # type: ignore[attr-defined]
    make.signer = server.signer  # type: ignore[attr-defined]
    yield make
    for component in made:
        component._cast_close()
    server.stop()
    system.close()
