"""How a client reaches its servers: TLS credentials, renewable tokens, reconnection backoff.

These are the pieces of the launch contract beyond the address and identity:

- ``CAST_TLS_CA`` (PEM of the CA that signed the servers' certificates; setting
  it turns TLS on), ``CAST_TLS_CERT`` and ``CAST_TLS_KEY`` (the client's own
  certificate and key, for servers that require client certificates), and
  ``CAST_TLS_SERVER_NAME`` (the name to check the server certificate against,
  when it differs from the host in the address);
- ``CAST_TOKEN_FILE``: a file holding the current token, rewritten by the
  orchestrator (or a Kubernetes token sidecar) before the token expires; the
  client re-reads it when it changes. When it is set it is the token, and
  ``CAST_TOKEN`` is not needed (:func:`read_token_file`).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import grpc

from cast.errors import InvalidArgumentError

__all__ = ["ClientTls", "TokenSource", "read_token_file"]


@dataclass(frozen=True)
class ClientTls:
    """TLS settings of a client: the CA to trust, and optionally a client certificate."""

    ca: Path
    cert: Path | None = None
    key: Path | None = None
    server_name: str = ""

    @classmethod
    def from_env(cls, env: Mapping[str, str]) -> ClientTls | None:
        """The settings in ``CAST_TLS_*`` variables; None without ``CAST_TLS_CA`` (plaintext)."""
        ca = env.get("CAST_TLS_CA")
        if not ca:
            if env.get("CAST_TLS_CERT") or env.get("CAST_TLS_KEY"):
                raise InvalidArgumentError("CAST_TLS_CERT/CAST_TLS_KEY given without CAST_TLS_CA: set the CA too")
            return None
        cert, key = env.get("CAST_TLS_CERT") or None, env.get("CAST_TLS_KEY") or None
        if bool(cert) != bool(key):
            raise InvalidArgumentError("set both CAST_TLS_CERT and CAST_TLS_KEY, or neither")
        return cls(Path(ca), Path(cert) if cert else None, Path(key) if key else None,
                   env.get("CAST_TLS_SERVER_NAME", ""))

    def env(self) -> dict[str, str]:
        """The ``CAST_TLS_*`` variables that :meth:`from_env` reads back, with absolute paths."""
        values = {"CAST_TLS_CA": str(self.ca.resolve())}
        if self.cert is not None and self.key is not None:
            values |= {"CAST_TLS_CERT": str(self.cert.resolve()), "CAST_TLS_KEY": str(self.key.resolve())}
        if self.server_name:
            values["CAST_TLS_SERVER_NAME"] = self.server_name
        return values

    def credentials(self) -> grpc.ChannelCredentials:
        """Channel credentials for gRPC; InvalidArgumentError naming a file that cannot be read."""
        try:
            ca = self.ca.read_bytes()
            cert = self.cert.read_bytes() if self.cert else None
            key = self.key.read_bytes() if self.key else None
        except OSError as exc:
            raise InvalidArgumentError(f"cannot read a TLS file (CAST_TLS_CA/CERT/KEY): {exc}") from exc
        return grpc.ssl_channel_credentials(root_certificates=ca, private_key=key, certificate_chain=cert)

    def channel_options(self) -> list[tuple[str, str]]:
        """Options that name the server to verify, if set."""
        return [("grpc.ssl_target_name_override", self.server_name)] if self.server_name else []


def read_token_file(path: str) -> str:
    """The token in the file ``CAST_TOKEN_FILE`` names, trimmed; InvalidArgumentError if it is empty or unreadable.

    The file is the renewed token, so when it is set it is the token, not ``CAST_TOKEN``: the same rule and
    words in the runners and the script paths of every language (connect_resolve.cc, ConnectResolver.java).
    """
    try:
        text = Path(path).read_text().strip()
        problem = "is empty"
    except (OSError, UnicodeDecodeError):
        text, problem = "", "cannot be read"
    if not text:
        raise InvalidArgumentError(f"CAST_TOKEN_FILE names {path}, which {problem}: point it at a token file "
                                   "(`cast run` renews one per component), or unset it")
    return text


class TokenSource:
    """The component's current token: fixed, or re-read from a file the orchestrator renews.

    The file is checked at most every ``check_interval`` seconds (one ``stat``),
    and re-read only when its modification time or size changed, so calls pay
    nothing measurable for renewal. An empty or unreadable file keeps the last token.
    """

    def __init__(self, token: str, path: str | os.PathLike[str] | None = None, check_interval: float = 1.0) -> None:
        self._token = token
        self._path = Path(path) if path else None
        self._interval = check_interval
        self._checked = 0.0
        self._stamp: tuple[int, int] | None = None
        self._lock = threading.Lock()
        if self._path is not None:
            self._refresh(force=True)

    @classmethod
    def from_file(cls, path: str) -> TokenSource:
        """The token of the file ``CAST_TOKEN_FILE`` names, re-read when renewed; :func:`read_token_file`'s error."""
        return cls(read_token_file(path), path)

    @property
    def path(self) -> Path | None:
        """The token file, if any."""
        return self._path

    def _refresh(self, force: bool = False) -> None:
        assert self._path is not None
        now = time.monotonic()
        if not force and now - self._checked < self._interval:
            return
        with self._lock:
            self._checked = now
            try:
                st = self._path.stat()
                stamp = (st.st_mtime_ns, st.st_size)
                if stamp != self._stamp:
                    text = self._path.read_text().strip()
                    if text:
                        self._token = text
                    self._stamp = stamp
            except OSError:
                pass  # keep the last token: the orchestrator may be replacing the file

    def refresh(self) -> bool:
        """Re-read the file now (after the server refused the token); True if the token changed."""
        if self._path is None:
            return False
        before = self._token
        self._refresh(force=True)
        return self._token != before

    def token(self) -> str:
        """The token to send now."""
        if self._path is not None:
            self._refresh()
        return self._token

    def metadata(self) -> tuple[tuple[str, str]]:
        """Call metadata carrying the current token."""
        return (("authorization", f"Bearer {self.token()}"),)
