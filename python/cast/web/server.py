"""The web view's socket (bound first) and uvicorn serving the app on it from a thread.

The socket is bound when :class:`WebServer` is made, before anything else
starts, so a taken port or a foreign address is the first thing said (and
``cast run --web`` stops before it starts anything). uvicorn then serves on
that very socket from a thread with its own event loop: the caller's thread
(and ``cast run``'s event loop, which serves the working memories) never
waits for a browser.
"""

from __future__ import annotations

import asyncio
import errno
import socket
import threading

import uvicorn
from starlette.applications import Starlette

from cast.listen import ListenAddress, ListenError
from cast.web.address import DEFAULT_LISTEN

__all__ = ["WebServer"]


def _bind(address: ListenAddress, option: str) -> socket.socket:
    try:
        family, kind, proto, _, where = socket.getaddrinfo(address.host, address.port, type=socket.SOCK_STREAM,
                                                           flags=socket.AI_PASSIVE)[0]
    except socket.gaierror as exc:
        raise ListenError(f"cannot listen on {address.host}:{address.port}: {exc.strerror}: give an address of this "
                          f"machine, such as {DEFAULT_LISTEN}") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(where)
        sock.listen(128)
    except OSError as exc:
        sock.close()
        here = f"{address.host}:{address.port}"
        if exc.errno == errno.EADDRINUSE:
            raise ListenError(f"cannot listen on {here}: the address is in use (another `cast web`, or another "
                              f"program): stop it, or give {option} {address.host}:PORT with a free port ({option} "
                              f"{address.host}:0 picks one and prints it)") from None
        raise ListenError(f"cannot listen on {here}: {exc.strerror}: give an address of this machine, such as "
                          f"{DEFAULT_LISTEN}") from None
    sock.setblocking(False)
    return sock


class WebServer:
    """A listening socket, bound now; :meth:`serve` runs an app on it on a thread; :meth:`close` ends both."""

    def __init__(self, address: ListenAddress, option: str = "--listen") -> None:
        self.address = address
        self._socket = _bind(address, option)
        self.port: int = self._socket.getsockname()[1]
        self._server: uvicorn.Server | None = None
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    @property
    def url(self) -> str:
        """``http://HOST:PORT`` with the bound port."""
        return self.address.url("http", self.port)

    def serve(self, app: Starlette) -> None:
        """Serve ``app`` on the bound socket from a thread of its own (returns at once)."""
        config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off",
                                timeout_graceful_shutdown=2, ws="none")
        server = self._server = uvicorn.Server(config)

        def body() -> None:
            try:
                asyncio.run(server.serve(sockets=[self._socket]))
            except Exception as exc:  # noqa: BLE001 - kept for the owner to say; a thread would only print it
                self.error = exc

        self._thread = threading.Thread(target=body, name="cast-web", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop serving (open pages are disconnected) and release the port. Once; later calls do nothing."""
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(10)
            self._thread = None
        self._socket.close()

