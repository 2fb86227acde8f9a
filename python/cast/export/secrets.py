"""The Secrets of an exported system: the system secret, and the TLS files when the system uses TLS.

The system secret signs every token. Under Kubernetes it is mounted only where
tokens are made or checked: the servers and each component's ``cast token``
init container and renewing sidecar, never a component's own container
(docs/deploy.md). It comes from ``--secret-file``, else ``$CAST_SECRET``, else
``$CAST_SECRET_FILE``, else the previous export into the same directory (so
that exporting again does not invalidate every running token), else a new
random one. The TLS files are split in two Secrets: the servers' (their
certificate and key, and the CA) and the components' (the CA, and the client
certificate and key when the servers require one), so that no component
container holds a server's private key.
"""

from __future__ import annotations

import base64
import hashlib
import secrets
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from cast.auth import TokenSigner
from cast.config.model import TlsConfig
from cast.errors import InvalidArgumentError

__all__ = [
    "SECRETS_FILE",
    "SECRET_KEY",
    "SYSTEM_SECRET",
    "TLS_CLIENT_SECRET",
    "TLS_SERVER_SECRET",
    "SecretSource",
    "fingerprint",
    "find_system_secret",
    "read_files",
    "secret_object",
    "tls_client_files",
    "tls_server_files",
]

SYSTEM_SECRET = "cast-secret"
TLS_SERVER_SECRET = "cast-tls-server"
TLS_CLIENT_SECRET = "cast-tls-client"
SECRET_KEY = "secret"
SECRETS_FILE = "secrets.yaml"  # the export's file holding the Secrets (read back to keep the system secret)


@dataclass(frozen=True)
class SecretSource:
    """The system secret and where it came from (said to the user)."""

    value: bytes
    origin: str


def find_system_secret(explicit: str | None, env: Mapping[str, str], out_dir: Path) -> SecretSource:
    """The secret to export: explicit file, environment, the previous export's, or a new one.

    InvalidArgumentError, saying where it came from, for one the servers would refuse (too short).
    """
    found = _find(explicit, env, out_dir)
    try:
        TokenSigner(found.value)
    except InvalidArgumentError as exc:
        raise InvalidArgumentError(f"the system secret {found.origin}: {exc.message}") from None
    return found


def _find(explicit: str | None, env: Mapping[str, str], out_dir: Path) -> SecretSource:
    if explicit:
        return SecretSource(_read(Path(explicit), "--secret-file"), f"from {explicit}")
    if env.get("CAST_SECRET"):
        return SecretSource(env["CAST_SECRET"].encode().strip(), "from $CAST_SECRET")
    if env.get("CAST_SECRET_FILE"):
        return SecretSource(_read(Path(env["CAST_SECRET_FILE"]), "$CAST_SECRET_FILE"), "from $CAST_SECRET_FILE")
    previous = _previous(out_dir / SECRETS_FILE)
    if previous:
        return SecretSource(previous, f"kept from the previous export ({out_dir / SECRETS_FILE})")
    return SecretSource(secrets.token_urlsafe(32).encode(), "new")


def _read(path: Path, what: str) -> bytes:
    try:
        value = path.read_bytes().strip()
    except OSError as exc:
        raise InvalidArgumentError(f"cannot read the system secret {path} ({what}): {exc.strerror}") from None
    if not value:
        raise InvalidArgumentError(f"the system secret {path} ({what}) is empty: put the secret in it (any "
                                   "random text, e.g. `head -c 32 /dev/urandom | base64`)")
    return value


def _previous(path: Path) -> bytes | None:
    """The system secret of an earlier export's Secret file, if there is one."""
    try:
        docs = list(yaml.safe_load_all(path.read_text()))
    except (OSError, yaml.YAMLError):
        return None
    for doc in docs:
        named = isinstance(doc, dict) and doc.get("metadata", {}).get("name") == SYSTEM_SECRET
        if named and doc.get("kind") == "Secret":
            data = doc.get("data", {}).get(SECRET_KEY)
            return base64.b64decode(data) if isinstance(data, str) else None
    return None


def fingerprint(value: bytes) -> str:
    """A short hash of the secret for pod annotations: a new secret restarts every pod that uses it."""
    return hashlib.sha256(value).hexdigest()[:16]


def secret_object(name: str, data: Mapping[str, bytes], labels: Mapping[str, str], namespace: str) -> dict[str, Any]:
    """An Opaque Secret holding ``data``."""
    return {
        "apiVersion": "v1",
        "kind": "Secret",
        "metadata": {"name": name, "namespace": namespace, "labels": dict(labels)},
        "type": "Opaque",
        "data": {key: base64.b64encode(value).decode() for key, value in data.items()},
    }


def tls_server_files(tls: TlsConfig) -> dict[str, Path]:
    """Secret key -> file, for the servers: what ``cast serve`` reads through the configuration's ``tls:``."""
    return {"ca": tls.ca, "cert": tls.cert, "key": tls.key}


def tls_client_files(tls: TlsConfig) -> dict[str, Path]:
    """Secret key -> file, for components and the servers' health probes: the CA, and a client identity if needed."""
    files = {"ca": tls.ca}
    if tls.client_auth:
        cert, key = tls.component_identity
        files |= {"cert": cert, "key": key}
    return files


def read_files(files: Mapping[str, Path]) -> dict[str, bytes]:
    """The contents of ``files``; InvalidArgumentError naming one that cannot be read."""
    out: dict[str, bytes] = {}
    for key, path in files.items():
        try:
            out[key] = path.read_bytes()
        except OSError as exc:
            raise InvalidArgumentError(f"cannot read the TLS file {path} ({exc.strerror})") from None
    return out
