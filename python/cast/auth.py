"""Component tokens: signed statements of a component's identity.

A token is ``<payload>.<signature>``, both base64url without padding; the
payload is JSON ``{"c": component id, "s": SA, "p": privileged, "iat": issued,
"exp": expiry or 0}`` and the signature is HMAC-SHA256 of the payload with the
system's secret. The orchestrator (or ``cast token``) holds the secret and
issues tokens; the server verifies them on every call. Identity therefore never
comes from a request field.

The secret is found, in order: an explicit path, ``$CAST_SECRET`` (the secret
itself), ``$CAST_SECRET_FILE``, then ``.cast/secret`` in the working directory,
which :func:`load_or_create_secret` creates (mode 0600) on first use.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import math
import os
import secrets
import time
from collections import OrderedDict
from pathlib import Path

from cast.core.records import Identity
from cast.errors import InvalidArgumentError, UnauthenticatedError

__all__ = [
    "DEFAULT_SECRET_PATH",
    "TokenSigner",
    "load_or_create_secret",
    "load_secret",
    "peek",
]

DEFAULT_SECRET_PATH = Path(".cast") / "secret"


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


class TokenSigner:
    """Issues and verifies tokens with one secret; caches verified tokens."""

    def __init__(self, secret: bytes) -> None:
        if len(secret) < 16:
            raise InvalidArgumentError("the token secret must be at least 16 bytes")
        self._secret = secret
        self._cache: OrderedDict[str, tuple[Identity, float]] = OrderedDict()

    def issue(self, identity: Identity, ttl_seconds: float = 0) -> str:
        """A token for ``identity``; it expires after ``ttl_seconds`` (0: never)."""
        now = time.time()
        payload = {
            "c": identity.component_id,
            "s": identity.subarchitecture,
            "p": identity.privileged,
            "iat": int(now),
            # Rounded up, so that a token lives at least ttl_seconds (renewal schedules rely on it).
            "exp": math.ceil(now + ttl_seconds) if ttl_seconds else 0,
        }
        body = _b64(json.dumps(payload, separators=(",", ":"), sort_keys=True).encode())
        return f"{body}.{self._sign(body)}"

    def _sign(self, body: str) -> str:
        return _b64(hmac.new(self._secret, body.encode("ascii"), hashlib.sha256).digest())

    def verify(self, token: str) -> Identity:
        """The identity a token states; UNAUTHENTICATED if it is malformed, forged or expired."""
        cached = self._cache.get(token)
        if cached is not None:
            identity, expiry = cached
            if not expiry or expiry > time.time():
                return identity
        body, dot, signature = token.partition(".")
        if not dot or not body or not signature:
            raise UnauthenticatedError("malformed token: expected '<payload>.<signature>'; get one from `cast token`")
        if not hmac.compare_digest(self._sign(body), signature):
            raise UnauthenticatedError(
                "token signature does not match: the token was forged, altered, or issued for another system "
                "(another secret); get one from `cast token` for this system"
            )
        try:
            payload = json.loads(_unb64(body))
            identity = Identity(str(payload["c"]), str(payload["s"]), bool(payload["p"]))
            expiry = float(payload.get("exp", 0))
        except (ValueError, KeyError, TypeError) as exc:
            raise UnauthenticatedError(f"malformed token payload: {exc}") from exc
        if expiry and expiry <= time.time():
            raise UnauthenticatedError(
                f"token of component '{identity.component_id}' expired at {time.ctime(expiry)}: get a new one"
            )
        self._cache[token] = (identity, expiry)
        if len(self._cache) > 4096:
            self._cache.popitem(last=False)
        return identity


def load_secret(path: str | os.PathLike[str] | None = None) -> bytes | None:
    """The secret from ``path``, ``$CAST_SECRET``, ``$CAST_SECRET_FILE`` or ``.cast/secret``; None if none."""
    if path is not None:
        return Path(path).read_bytes().strip()
    env = os.environ.get("CAST_SECRET")
    if env:
        return env.encode()
    env_file = os.environ.get("CAST_SECRET_FILE")
    if env_file:
        return Path(env_file).read_bytes().strip()
    if DEFAULT_SECRET_PATH.exists():
        return DEFAULT_SECRET_PATH.read_bytes().strip()
    return None


def load_or_create_secret(path: str | os.PathLike[str] | None = None) -> bytes:
    """Like :func:`load_secret`, but create ``.cast/secret`` (or ``path``) with a random secret if none exists."""
    if path is not None and not Path(path).exists():
        target = Path(path)
    else:
        found = load_secret(path)
        if found is not None:
            return found
        target = DEFAULT_SECRET_PATH
    target.parent.mkdir(parents=True, exist_ok=True)
    secret = secrets.token_urlsafe(32).encode()
    fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(secret + b"\n")
    return secret


def peek(token: str) -> Identity | None:
    """The identity a token claims, without verifying it (clients use it to learn their own flags)."""
    try:
        payload = json.loads(_unb64(token.partition(".")[0]))
        return Identity(str(payload["c"]), str(payload["s"]), bool(payload["p"]))
    except (ValueError, KeyError, TypeError):
        return None
