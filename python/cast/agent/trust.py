"""Whom an agent obeys: a client certificate signed by its CA, and/or a token signed with a system secret.

An agent starts processes on its host for whoever calls it, so it refuses to
run without a way to tell its orchestrator from anyone else: ``--tls-ca``
(mutual TLS, the handshake refuses a client without a certificate signed by
that CA) or ``--secret-file`` (every call carries ``authorization: Bearer
<token>``, a privileged token for the identity :data:`cast.orchestrator.agent_link.ORCHESTRATOR_ID` signed
with that secret; :mod:`cast.auth`), or both. The check is an interceptor, so
it covers every service, reflection included; the health service stays open
(it reveals nothing and starts nothing), so that probes need no token.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
from grpc_health.v1 import health_pb2

from cast.auth import TokenSigner, load_secret
from cast.core.calls import CALLS, Credential
from cast.errors import CastError, InvalidArgumentError, UnauthenticatedError
from cast.orchestrator.agent_link import ORCHESTRATOR_ID

__all__ = ["AgentTrust", "TrustInterceptor"]

_OPEN_SERVICES = (health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,)


@dataclass(frozen=True)
class AgentTrust:
    """The agent's TLS files and token secret (at least a CA or a secret)."""

    signer: TokenSigner | None = None
    secret_file: Path | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None
    tls_ca: Path | None = None

    @classmethod
    def from_files(
        cls, secret_file: str | None, tls_cert: str | None, tls_key: str | None, tls_ca: str | None
    ) -> AgentTrust:
        """Trust from the command line's files; InvalidArgumentError saying what is missing."""
        if secret_file is None and tls_ca is None:
            raise InvalidArgumentError(
                "an agent starts processes for whoever calls it, so it needs a way to trust its orchestrator: "
                "give --tls-ca CA.pem (with --tls-cert/--tls-key: mutual TLS) or --secret-file FILE (the "
                "system secret; calls carry a token signed with it), or both"
            )
        if (tls_cert is None) != (tls_key is None) or (tls_ca is not None and tls_cert is None):
            raise InvalidArgumentError("TLS needs both --tls-cert and --tls-key (and --tls-ca for mutual TLS)")
        signer = None
        if secret_file is not None:
            try:
                secret = load_secret(secret_file)
            except OSError as exc:
                raise InvalidArgumentError(f"cannot read the secret file {secret_file}: {exc.strerror}") from exc
            assert secret is not None
            signer = TokenSigner(secret)
        return cls(signer, _path(secret_file), _path(tls_cert), _path(tls_key), _path(tls_ca))

    def credentials(self) -> grpc.ServerCredentials | None:
        """The server's TLS credentials (client certificates required with a CA); None for plaintext."""
        if self.tls_cert is None or self.tls_key is None:
            return None
        try:
            pair = (self.tls_key.read_bytes(), self.tls_cert.read_bytes())
            ca = self.tls_ca.read_bytes() if self.tls_ca is not None else None
        except OSError as exc:
            raise InvalidArgumentError(f"cannot read the agent's TLS files: {exc}") from exc
        return grpc.ssl_server_credentials([pair], root_certificates=ca, require_client_auth=ca is not None)

    def describe(self) -> str:
        """How this agent trusts callers, for its first output line."""
        parts = []
        if self.tls_ca is not None:
            parts.append(f"mutual TLS (client certificates signed by {self.tls_ca})")
        elif self.tls_cert is not None:
            parts.append("TLS")
        if self.secret_file is not None:
            parts.append(f"tokens signed with the secret in {self.secret_file}")
        return " + ".join(parts)

    def check(self, metadata: tuple[tuple[str, str | bytes], ...] | None) -> None:
        """UnauthenticatedError unless the call carries the token this agent wants (if it wants one)."""
        if self.signer is None:
            return  # mutual TLS only: the handshake already refused any client without a certificate
        header = next((v for k, v in metadata or () if k == "authorization"), None)
        if header is None:
            raise UnauthenticatedError(
                "missing 'authorization: Bearer <token>': this agent needs a privileged token for "
                f"'{ORCHESTRATOR_ID}' signed with its system secret"
            )
        text = header.decode() if isinstance(header, bytes) else header
        scheme, _, token = text.partition(" ")
        if scheme.lower() != "bearer" or not token:
            raise UnauthenticatedError("the authorization header must be 'Bearer <token>'")
        identity = self.signer.verify(token.strip())
        if identity.component_id != ORCHESTRATOR_ID or not identity.privileged:
            raise UnauthenticatedError(
                f"{identity.describe()} may not use this agent: only a privileged token for "
                f"'{ORCHESTRATOR_ID}' signed with the system secret may"
            )


def _path(text: str | None) -> Path | None:
    return Path(text) if text is not None else None


class TrustInterceptor(grpc.aio.ServerInterceptor):  # type: ignore[type-arg]
    """Refuses, UNAUTHENTICATED, every call the agent's trust does not accept (health aside)."""

    def __init__(self, trust: AgentTrust) -> None:
        self._trust = trust

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[Any]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> Any:
        """The real handler for a trusted call; one that aborts for any other."""
        call = handler_call_details.method.strip("/")
        if call.partition("/")[0] in _OPEN_SERVICES:
            return await continuation(handler_call_details)
        # The agent's calls need the orchestrator (cast.core.calls); so does what else it serves (reflection).
        needs = CALLS.get(call, Credential.ORCHESTRATOR)
        if needs is not Credential.ORCHESTRATOR:
            return _refusal(await continuation(handler_call_details), f"an agent does not serve {call}")
        try:
            self._trust.check(handler_call_details.invocation_metadata)
        except CastError as exc:
            return _refusal(await continuation(handler_call_details), exc.message)
        return await continuation(handler_call_details)


def _refusal(handler: Any, message: str) -> Any:
    """A handler of the same shape as ``handler`` that aborts UNAUTHENTICATED without reading the request."""
    if handler is None:
        return None

    async def deny(request: Any, context: grpc.aio.ServicerContext[Any, Any]) -> None:
        await context.abort(grpc.StatusCode.UNAUTHENTICATED, message)

    if handler.request_streaming and handler.response_streaming:
        return grpc.stream_stream_rpc_method_handler(deny)
    if handler.request_streaming:
        return grpc.stream_unary_rpc_method_handler(deny)
    if handler.response_streaming:
        return grpc.unary_stream_rpc_method_handler(deny)
    return grpc.unary_unary_rpc_method_handler(deny)
