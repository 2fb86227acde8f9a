"""A server with shared memory on, in a thread of the test's process, and components of it over gRPC.

The harness of the shared-memory tests (test_shared_memory, test_socket_*,
test_session_writes): :class:`Host` and its ``host`` fixture, and the test
images. A test module takes the fixture by importing it by name.
"""

from __future__ import annotations

import gc
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.auth import TokenSigner
from cast.client import shm, shm_session
from cast.client.grpc_transport import GrpcTransport
from cast.core.journal import Journal
from cast.core.records import Identity, Limits
from cast.core.shared import SharedSettings
from cast.core.system import System
from cast.server.wire import wire_system
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import working_memory_pb2_grpc as wm_grpc
from tests.client.conftest import ThreadServer

__all__ = ["BYTES_VALUE", "MIB", "Host", "host", "image"]

MIB = 1 << 20
BYTES_VALUE = "google.protobuf.BytesValue"


class Host:
    """A server with shared memory, and components of it over gRPC."""

    def __init__(self, tmp_path: Path, settings: SharedSettings | None = None, limits: Limits | None = None,
                 journal: bool = False) -> None:
        self.journal = journal
        self.tmp_path = tmp_path
        self.settings = settings or SharedSettings()
        self.limits = limits or Limits()
        self.system = self._system()
        self.server = ThreadServer(self.system)
        assert self.server.running is not None
        self.endpoint = self.server.running.endpoint
        self.signer: TokenSigner = self.server.signer
        self.made: list[cast.Component] = []
        self.channel = grpc.insecure_channel(self.endpoint)

    def _system(self) -> System:
        journal = Journal(self.tmp_path / "wm.db", "batch", 64) if self.journal else None
        return wire_system("t", ["vision", "language"], limits=self.limits, journal=journal,
                           shared_memory=self.settings)

    def component(self, cid: str, sa: str = "vision", privileged: bool = False) -> Any:
        identity = Identity(cid, sa, privileged)
        c = cast.UnmanagedComponent()
        transport = GrpcTransport(self.endpoint, self.signer.issue(identity), identity)
        c._cast_bind(transport)
        self.made.append(c)
        transport._directory.shared.session()  # its session, or its fallback, now (as its first large call would)
        return c

    def metadata(self, cid: str, sa: str = "vision") -> tuple[tuple[str, str], ...]:
        return (("authorization", f"Bearer {self.signer.issue(Identity(cid, sa))}"),)

    def session(self, cid: str, sa: str = "vision") -> shm_session.ClientSession:
        """A raw session of ``cid``, as any client opens one."""
        info = dir_grpc.DirectoryStub(self.channel).DescribeSystem(dir_pb2.DescribeSystemRequest(),
                                                                    metadata=self.metadata(cid, sa)).shared_memory
        return shm.connect(info, self.signer.issue(Identity(cid, sa)), self.endpoint)

    def link(self, cid: str) -> Any:
        """The server's connection of ``cid``'s one shared-memory session."""
        shared = self.system.shared
        assert shared is not None
        (link,) = [s.link for s in shared.sessions.values() if s.who.component_id == cid]
        assert link is not None
        return link

    def stub(self) -> wm_grpc.WorkingMemoryStub:
        return wm_grpc.WorkingMemoryStub(self.channel)

    def shared(self) -> dict[str, int]:
        assert self.system.shared is not None
        gc.collect()
        return self.system.shared.snapshot()

    def close(self) -> None:
        for c in self.made:
            c._cast_close()
        self.channel.close()
        self.server.stop()
        self.system.close()


@pytest.fixture
def host(tmp_path: Path) -> Iterator[Callable[..., Host]]:
    made: list[Host] = []

    def make(**options: Any) -> Host:
        made.append(Host(tmp_path, **options))
        return made[-1]

    yield make
    for h in made:
        h.close()


def image(size: int, seed: int = 0) -> BytesValue:
    return BytesValue(value=bytes((seed + i) % 251 for i in range(256)) * (size // 256))
