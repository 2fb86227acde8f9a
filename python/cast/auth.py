"""Component tokens: signed statements of a component's identity, as standard JWTs.

A token is a JSON Web Token (RFC 7519) signed with HS256 (HMAC-SHA256) and the
system's secret, so any language's JWT library reads it. Its claims:
``{"c": component id, "s": SA, "p": privileged, "iat": issued}`` and, when it
expires, ``"exp"``. The orchestrator (or ``cast token``) holds the secret and
issues tokens; the server verifies them on every call. Identity therefore never
comes from a request field. Tokens of the format before JWTs
(``<payload>.<signature>``) are refused with a message that says to re-issue them.

The secret is found, in order: an explicit path, ``$CAST_SECRET`` (the secret
itself), ``$CAST_SECRET_FILE``, then ``.cast/secret`` in the working directory,
which :func:`load_or_create_secret` creates (mode 0600) on first use.
"""

from __future__ import annotations

import base64
import contextlib
import json
import math
import os
import secrets
import time
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType

from cast.core.records import Identity
from cast.errors import InvalidArgumentError, UnauthenticatedError

__all__ = [
    "DEFAULT_SECRET_PATH",
    "TokenSigner",
    "load_or_create_secret",
    "load_secret",
    "peek",
    "write_token_file",
]

DEFAULT_SECRET_PATH = Path(".cast") / "secret"
_ALGORITHM = "HS256"


def _jwt() -> ModuleType:
    # Imported when a token is made or checked, not with this module: PyJWT loads the cryptography
    # package (~0.2 s of CPU), and a component that only carries the token it was given never needs it.
    import jwt

    return jwt
_MIN_SECRET = 32


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


class TokenSigner:
    """Issues and verifies tokens with one secret; caches verified tokens."""

    def __init__(self, secret: bytes) -> None:
        if len(secret) < _MIN_SECRET:
            # RFC 7518 (3.2): an HS256 key must be at least as long as the hash, 256 bits.
            raise InvalidArgumentError(
                f"the token secret is {len(secret)} bytes, shorter than {_MIN_SECRET}: HS256 needs at least "
                "32 bytes; make one with `python -c 'import secrets; print(secrets.token_urlsafe(32))'`, or let "
                "`cast serve`/`cast run` create it"
            )
        self._secret = secret
        self._cache: OrderedDict[str, tuple[Identity, float]] = OrderedDict()

    def issue(self, identity: Identity, ttl_seconds: float = 0) -> str:
        """A token for ``identity``; it expires after ``ttl_seconds`` (0: never)."""
        now = time.time()
        claims: dict[str, object] = {
            "c": identity.component_id,
            "s": identity.subarchitecture,
            "p": identity.privileged,
            "iat": int(now),
        }
        if ttl_seconds:
            # Rounded up, so that a token lives at least ttl_seconds (renewal schedules rely on it).
            claims["exp"] = math.ceil(now + ttl_seconds)
        token: str = _jwt().encode(claims, self._secret, algorithm=_ALGORITHM)
        return token

    def verify(self, token: str) -> Identity:
        """The identity a token states; UNAUTHENTICATED if it is malformed, forged or expired."""
        return self.verify_until(token)[0]

    def verify_until(self, token: str) -> tuple[Identity, float]:
        """The identity a token states and when it expires (seconds since the epoch; 0: never), as :meth:`verify`.

        A token's answer is the same until it expires (the secret is fixed for
        the signer's life), so a caller that holds the token, as a stream's
        metadata does, may keep the identity until then and verify again after.
        """
        cached = self._cache.get(token)
        if cached is not None:
            identity, expiry = cached
            if not expiry or expiry > time.time():
                return cached
        if token.count(".") == 1:
            raise UnauthenticatedError(
                "token in the format before JWTs ('<payload>.<signature>'): tokens are JSON Web Tokens now; "
                "re-issue it with `cast token` (or restart the component under `cast run`)"
            )
        jwt = _jwt()
        try:
            claims = jwt.decode(
                token, self._secret, algorithms=[_ALGORITHM], options={"require": ["c", "s", "p", "iat"]}
            )
        except jwt.ExpiredSignatureError:
            claimed = peek(token)
            who = f" of component '{claimed.component_id}'" if claimed else ""
            raise UnauthenticatedError(f"token{who} expired: get a new one (`cast token`)") from None
        except jwt.InvalidSignatureError:
            raise UnauthenticatedError(
                "token signature does not match: the token was forged, altered, or issued for another system "
                "(another secret); get one from `cast token` for this system"
            ) from None
        except jwt.InvalidTokenError as exc:
            raise UnauthenticatedError(
                f"malformed token ({exc}): expected a JWT signed with HS256; get one from `cast token`"
            ) from None
        try:
            identity = Identity(_text(claims["c"]), _text(claims["s"]), _flag(claims["p"]))
        except (TypeError, ValueError) as exc:
            raise UnauthenticatedError(f"malformed token claims: {exc}") from None
        expiry = float(claims.get("exp", 0))
        self._cache[token] = (identity, expiry)
        if len(self._cache) > 4096:
            self._cache.popitem(last=False)
        return identity, expiry


def _text(value: object) -> str:
    if not isinstance(value, str):
        raise TypeError(f"expected a string, got {type(value).__name__}")
    return value


def _flag(value: object) -> bool:
    if not isinstance(value, bool):
        raise TypeError(f"'p' must be true or false, got {value!r}")
    return value


def load_secret(path: str | os.PathLike[str] | None = None, env: Mapping[str, str] | None = None) -> bytes | None:
    """The secret from ``path``, ``$CAST_SECRET``, ``$CAST_SECRET_FILE`` or ``.cast/secret``; None if none.

    ``env``: where the variables are looked up (default ``os.environ``).
    """
    if path is not None:
        return Path(path).read_bytes().strip()
    env = os.environ if env is None else env
    secret = env.get("CAST_SECRET")
    if secret:
        return secret.encode()
    env_file = env.get("CAST_SECRET_FILE")
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


def write_token_file(path: Path, token: str) -> None:
    """Write ``token`` to ``path`` (mode 0600, in a 0700 directory made if missing), atomically.

    Client libraries re-read the file while the component runs (``CAST_TOKEN_FILE``):
    writing a temporary file and renaming it means they read the old token or the
    new one, never half a file.
    """
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_suffix(".tmp")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    tmp.replace(path)


def peek(token: str) -> Identity | None:
    """The identity a token claims, without verifying it (clients use it to learn their own flags)."""
    try:
        claims = json.loads(_unb64(token.split(".")[1]))
        return Identity(str(claims["c"]), str(claims["s"]), bool(claims["p"]))
    except (ValueError, KeyError, TypeError, IndexError):
        return None
