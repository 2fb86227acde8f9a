"""``python -m cast.export.health_probe HOST:PORT --ca CA``: a server's gRPC health over TLS, for Kubernetes.

kubelet's own ``grpc`` probe speaks plaintext only, so the manifests of a
system with ``tls:`` probe its servers with this instead, run inside the
server's container against 127.0.0.1. It asks the standard health service
(``grpc.health.v1.Health/Check``, the whole server: service "") and exits 0 if
the answer is SERVING, 1 otherwise, saying why on one line. The server's
certificate is checked against ``--server-name``, the name components dial
(the server's Service), so a probe passes only with a certificate that the
components will accept too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

__all__ = ["check", "main"]


def check(address: str, server_name: str, ca: Path, cert: Path | None = None, key: Path | None = None,
          timeout: float = 3.0) -> str:
    """What is wrong with the server at ``address`` over TLS: "" when it answers SERVING."""
    try:
        credentials = grpc.ssl_channel_credentials(
            root_certificates=ca.read_bytes(),
            private_key=key.read_bytes() if key else None,
            certificate_chain=cert.read_bytes() if cert else None,
        )
    except OSError as exc:
        return f"cannot read a TLS file: {exc}"
    options = [("grpc.ssl_target_name_override", server_name)]
    with grpc.secure_channel(address, credentials, options=options) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        try:
            answer = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=timeout)
        except grpc.RpcError as exc:
            return f"{exc.code().name}: {exc.details()}"
    if answer.status != health_pb2.HealthCheckResponse.SERVING:
        return f"not serving: {health_pb2.HealthCheckResponse.ServingStatus.Name(answer.status)}"
    return ""


def main(argv: list[str] | None = None) -> int:
    """Exit 0 if the server is serving, 1 if not (with the reason on standard error)."""
    parser = argparse.ArgumentParser(prog="python -m cast.export.health_probe", description=__doc__.split("\n")[0])
    parser.add_argument("address", help="HOST:PORT of the server (127.0.0.1:PORT inside its pod)")
    parser.add_argument("--server-name", required=True, help="the name the server's certificate must have")
    parser.add_argument("--ca", required=True, type=Path, help="the CA that signed the server's certificate")
    parser.add_argument("--cert", type=Path, help="a client certificate, for servers that require one")
    parser.add_argument("--key", type=Path, help="the client certificate's key")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the answer")
    args = parser.parse_args(argv)
    problem = check(args.address, args.server_name, args.ca, args.cert, args.key, args.timeout)
    if problem:
        print(f"health of {args.address}: {problem}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
