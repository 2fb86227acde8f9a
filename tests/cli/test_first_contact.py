"""A tool's first contact with a system: a connection dropped once is tried again, an absent system is said fast."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import pytest

from cast.cli.connect import FIRST_CONTACT_S, SystemClient
from cast.errors import UnavailableError
from tests.conftest import ServerHandle
from tests.reliability.proxy import Proxy


@pytest.fixture
def relay(server: ServerHandle) -> Iterator[Proxy]:
    """A relay to the server that closes the first connection it accepts at once (a dropped handshake)."""
    r = Proxy(server.endpoint)
    r.drop_next = 1
    yield r
    r.close()


def test_a_connection_dropped_once_is_tried_again(server: ServerHandle, relay: Proxy) -> None:
    client = SystemClient(relay.endpoint, server.token("cast-cli", "vision", privileged=True))
    try:
        assert client.subarchitectures == ["vision", "language", "motor"]
        assert relay.drop_next == 0  # the first connection was dropped: the answer came on another
    finally:
        client.close()


def test_no_system_is_said_within_the_first_contact_time() -> None:
    with socket.socket() as bound:  # a port of ours that nobody listens on: connections are refused
        bound.bind(("127.0.0.1", 0))
        started = time.monotonic()
        with pytest.raises(UnavailableError, match="server unavailable"):
            SystemClient(f"127.0.0.1:{bound.getsockname()[1]}", "token")
        assert time.monotonic() - started < FIRST_CONTACT_S + 5  # stated bound: the retries, then gRPC's own call
