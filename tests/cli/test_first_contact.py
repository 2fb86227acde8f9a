"""A tool's first contact with a system: a connection dropped once is tried again, an absent system is said fast."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import pytest

from cast.cli.connect import FIRST_CONTACT_S, SystemClient
from cast.errors import UnavailableError
from tests.conftest import ServerHandle


class _DropsFirstConnection:
    """A TCP relay to ``target`` that at once closes the first connection it accepts (a dropped handshake)."""

    def __init__(self, target: str) -> None:
        host, port = target.rsplit(":", 1)
        self._target = (host, int(port))
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = f"127.0.0.1:{self._listener.getsockname()[1]}"
        self.accepted = 0
        self._sockets: list[socket.socket] = [self._listener]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return  # closed
            self.accepted += 1
            if self.accepted == 1:
                client.close()
                continue
            upstream = socket.create_connection(self._target)
            self._sockets += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        for s in self._sockets:
            s.close()


@pytest.fixture
def relay(server: ServerHandle) -> Iterator[_DropsFirstConnection]:
    r = _DropsFirstConnection(server.endpoint)
    yield r
    r.close()


def test_a_connection_dropped_once_is_tried_again(server: ServerHandle, relay: _DropsFirstConnection) -> None:
    client = SystemClient(relay.endpoint, server.token("cast-cli", "vision", privileged=True))
    try:
        assert client.subarchitectures == ["vision", "language", "motor"]
        assert relay.accepted >= 2
    finally:
        client.close()


def test_no_system_is_said_within_the_first_contact_time() -> None:
    with socket.socket() as bound:  # a port of ours that nobody listens on: connections are refused
        bound.bind(("127.0.0.1", 0))
        started = time.monotonic()
        with pytest.raises(UnavailableError, match="server unavailable"):
            SystemClient(f"127.0.0.1:{bound.getsockname()[1]}", "token")
        assert time.monotonic() - started < FIRST_CONTACT_S + 5  # stated bound: the retries, then gRPC's own call
