"""Finding and reaching a running system from a tool (``cast ls``, ``cast token``, ...).

The address: ``--endpoint``, else ``$CAST_ENDPOINT``, else the ``system.json``
that ``cast run`` writes in its runtime directory. The identity: ``$CAST_TOKEN``
if set, else a token for ``cast-cli`` (no SA, not privileged: reads only)
issued from the system's secret: ``--secret-file``, ``$CAST_SECRET``,
``$CAST_SECRET_FILE``, the runtime directory's ``secret``, ``.cast/secret``.
TLS: ``--tls-ca`` (with ``--tls-cert``/``--tls-key`` for servers that require
client certificates), else the ``$CAST_TLS_*`` variables of the launch
contract, else the ``tls`` block ``cast run`` records in ``system.json``;
none of these means plaintext.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc

from cast.auth import TokenSigner
from cast.client.credentials import ClientTls
from cast.client.discovery import NoSystemError, find_endpoint, find_secret, find_tls
from cast.client.grpc_transport import CHANNEL_OPTIONS, map_rpc_error
from cast.core.records import Identity
from cast.errors import CastError, NotFoundError
from cast.runtime_dir import RuntimeDir, default_runtime_dir
from cast.v1 import directory_pb2 as dir_pb2
from cast.v1 import directory_pb2_grpc as dir_grpc
from cast.v1 import inspection_pb2_grpc as insp_grpc
from cast.v1 import task_manager_pb2_grpc as tm_grpc
from cast.v1 import working_memory_pb2_grpc as wm_grpc

__all__ = [
    "FIRST_CONTACT_S", "TOOL_ID", "NoSystemError", "ServerStubs", "SystemClient", "find_endpoint", "find_secret",
    "find_tls", "tool_token", "add_tls_options",
]

TOOL_ID = "cast-cli"


def tool_token(secret_file: str | None, runtime: RuntimeDir, env: Mapping[str, str]) -> str:
    """The tool's token: made from ``--secret-file``, else ``$CAST_TOKEN``, else made from the system's secret.

    A flag on the command line beats the environment; a token made from a
    secret is a read-only ``cast-cli`` one for an hour.
    """
    if env.get("CAST_TOKEN") and not secret_file:
        return env["CAST_TOKEN"]
    return TokenSigner(find_secret(secret_file, runtime, env)).issue(Identity(TOOL_ID, "", False), 3600)


@dataclass
class ServerStubs:
    """The stubs of one server."""

    endpoint: str
    channel: grpc.Channel
    wm: wm_grpc.WorkingMemoryStub
    tm: tm_grpc.TaskManagerStub
    directory: dir_grpc.DirectoryStub
    inspection: insp_grpc.InspectionStub


FIRST_CONTACT_S = 1.0
"""How long a tool tries to reach the system before it says none answers (gRPC reconnects every 0.1 s)."""


class SystemClient:
    """A tool's connection to a running system: the directory and every server it names."""

    def __init__(self, endpoint: str, token: str, timeout: float = 10.0, tls: ClientTls | None = None) -> None:
        self.metadata = (("authorization", f"Bearer {token}"),)
        self.timeout = timeout
        self.tls = tls
        self._credentials = tls.credentials() if tls is not None else None
        self._options = [*CHANNEL_OPTIONS, *(tls.channel_options() if tls is not None else [])]
        self._servers: dict[str, ServerStubs] = {}
        self.directory = self._stubs(endpoint)
        self.system = self._first_contact()

    def _first_contact(self) -> dir_pb2.SystemDescription:
        """DescribeSystem, tried again while UNAVAILABLE for up to :data:`FIRST_CONTACT_S`.

        A connection that fails once (a handshake a busy server dropped, a
        server still starting) does not make the tool say "no system answers";
        a system that is not there, or speaks TLS to a plaintext tool, still
        gets that error, the first attempt's, after FIRST_CONTACT_S.
        """
        end = time.monotonic() + FIRST_CONTACT_S
        delay = 0.1
        first: CastError | None = None
        while True:
            try:
                described: dir_pb2.SystemDescription = self.call(self.directory.directory.DescribeSystem,
                                                                 dir_pb2.DescribeSystemRequest())
                return described
            except CastError as exc:
                if exc.code != "UNAVAILABLE":
                    raise
                first = first or exc
                if time.monotonic() + delay > end:
                    raise first from None
            time.sleep(delay)
            delay *= 2

    def _stubs(self, endpoint: str) -> ServerStubs:
        stubs = self._servers.get(endpoint)
        if stubs is None:
            if self._credentials is None:
                channel = grpc.insecure_channel(endpoint, options=self._options)
            else:
                channel = grpc.secure_channel(endpoint, self._credentials, options=self._options)
            stubs = ServerStubs(
                endpoint, channel, wm_grpc.WorkingMemoryStub(channel), tm_grpc.TaskManagerStub(channel),
                dir_grpc.DirectoryStub(channel), insp_grpc.InspectionStub(channel),
            )
            self._servers[endpoint] = stubs
        return stubs

    def call(self, method: Any, request: Any) -> Any:
        """Call a unary method with the tool's token; the named CastError on failure."""
        try:
            return method(request, metadata=self.metadata, timeout=self.timeout)
        except grpc.RpcError as exc:
            raise map_rpc_error(exc) from None

    @property
    def subarchitectures(self) -> list[str]:
        """Every SA of the system, in the directory's order."""
        return [sa.name for sa in self.system.subarchitectures]

    def server(self, sa: str) -> ServerStubs:
        """The server hosting an SA; NotFoundError naming the known SAs."""
        for info in self.system.subarchitectures:
            if info.name == sa:
                same = not info.endpoint or info.endpoint == self.system.endpoint
                return self.directory if same else self._stubs(info.endpoint)
        raise NotFoundError(f"no subarchitecture '{sa}' (known: {', '.join(self.subarchitectures)})")

    def servers(self) -> list[tuple[ServerStubs, list[str]]]:
        """Each server with the SAs it hosts."""
        out: dict[str, tuple[ServerStubs, list[str]]] = {}
        for sa in self.subarchitectures:
            stubs = self.server(sa)
            out.setdefault(stubs.endpoint, (stubs, []))[1].append(sa)
        return list(out.values())

    def close(self) -> None:
        """Close every channel."""
        for stubs in self._servers.values():
            stubs.channel.close()

    def __enter__(self) -> SystemClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def connect(args: Any, env: Mapping[str, str] | None = None) -> SystemClient:
    """A :class:`SystemClient` from the common tool options (endpoint, runtime dir, secret, TLS)."""
    env = os.environ if env is None else env
    runtime = RuntimeDir(Path(args.runtime_dir) if args.runtime_dir else default_runtime_dir(env))
    endpoint = find_endpoint(args.endpoint, runtime, env)
    tls = find_tls(args, runtime, env)
    try:
        return SystemClient(endpoint, tool_token(args.secret_file, runtime, env), tls=tls)
    except CastError as exc:
        if exc.code == "UNAVAILABLE":
            raise NoSystemError(f"no system answers at {endpoint}: {exc.message}{_tls_hint(tls)}") from None
        raise


def _tls_hint(tls: ClientTls | None) -> str:
    # A TLS/plaintext mismatch shows up only as an unavailable server; say which side to check.
    if tls is None:
        return (" (this tool spoke plaintext: if the system uses TLS, give --tls-ca CA.pem, or set CAST_TLS_CA)")
    return (f" (this tool spoke TLS, trusting {tls.ca}: check that the server uses TLS with a certificate signed "
            "by that CA, and give --tls-cert/--tls-key if it requires client certificates)")


def add_tls_options(parser: Any) -> None:
    """The ``--tls-*`` options of a tool that connects to a running system."""
    parser.add_argument("--tls-ca", help="PEM of the CA that signed the servers' certificates; turns TLS on "
                                         "(default: $CAST_TLS_CA, else what the running `cast run` recorded)")
    parser.add_argument("--tls-cert", help="client certificate (PEM), for servers that require one")
    parser.add_argument("--tls-key", help="client key (PEM), with --tls-cert")
    parser.add_argument("--tls-server-name", help="name to check the server certificate against, when it differs "
                                                  "from the host in the address")
