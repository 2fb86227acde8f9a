"""Finding a running system from outside it: its address, its secret, its TLS settings.

Shared by the tools (``cast ls``, ``cast token``, ...) and by :func:`cast.connect`.
The address: an explicit one, else ``$CAST_ENDPOINT``, else the ``system.json``
that ``cast run`` writes in its runtime directory. The secret: an explicit
file, ``$CAST_SECRET``, ``$CAST_SECRET_FILE``, the runtime directory's
``secret``, ``.cast/secret``. TLS: explicit options, else the ``$CAST_TLS_*``
variables of the launch contract, else the ``tls`` block of ``system.json``;
none of these means plaintext.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cast.auth import load_secret
from cast.client.credentials import ClientTls
from cast.errors import InvalidArgumentError, NotFoundError
from cast.runtime_dir import RuntimeDir

__all__ = ["NoSystemError", "find_endpoint", "find_secret", "find_tls", "first_subarchitecture"]


class NoSystemError(NotFoundError):
    """No running system could be found."""


def find_endpoint(explicit: str | None, runtime: RuntimeDir, env: Mapping[str, str]) -> str:
    """The directory address of the running system."""
    if explicit:
        return explicit
    if env.get("CAST_ENDPOINT"):
        return env["CAST_ENDPOINT"]
    state = runtime.read_state()
    if state is not None:
        return str(state["endpoint"])
    raise NoSystemError(
        f"no running system found: none recorded in {runtime.state_path}; start one with `cast run CONFIG`, "
        "or give --endpoint HOST:PORT (or set CAST_ENDPOINT)"
    )


def find_secret(explicit: str | None, runtime: RuntimeDir, env: Mapping[str, str]) -> bytes:
    """The token secret of the running system."""
    if explicit:
        return Path(explicit).read_bytes().strip()
    if env.get("CAST_SECRET") or env.get("CAST_SECRET_FILE"):
        found = load_secret(env=env)
        if found:
            return found
    secret = runtime.read_secret() or load_secret(env=env)
    if secret is None:
        raise NoSystemError(
            f"no token secret: none in {runtime.secret_path} (written by a running `cast run`); pass --secret-file, "
            "or set CAST_SECRET"
        )
    return secret


def find_tls(args: Any, runtime: RuntimeDir, env: Mapping[str, str]) -> ClientTls | None:
    """The TLS settings to reach the system with, or None for plaintext."""
    ca, cert, key = (getattr(args, name, None) for name in ("tls_ca", "tls_cert", "tls_key"))
    if ca or cert or key:
        if not ca:
            raise InvalidArgumentError("--tls-cert/--tls-key given without --tls-ca: give the CA that signed the "
                                       "server's certificate too")
        if bool(cert) != bool(key):
            raise InvalidArgumentError("give both --tls-cert and --tls-key, or neither")
        return ClientTls(Path(ca), Path(cert) if cert else None, Path(key) if key else None,
                         getattr(args, "tls_server_name", None) or "")
    from_env = ClientTls.from_env(env)
    if from_env is not None:
        return from_env
    state = runtime.read_state()
    recorded = state.get("tls") if state else None
    if recorded:
        return ClientTls(Path(recorded["ca"]), Path(recorded["cert"]) if recorded.get("cert") else None,
                         Path(recorded["key"]) if recorded.get("key") else None)
    return None


def first_subarchitecture(runtime: RuntimeDir) -> str:
    """The first SA of the first server the running ``cast run`` recorded; "" if none is recorded."""
    state = runtime.read_state()
    for server in (state or {}).get("servers", {}).values():
        for sa in server.get("subarchitectures", []):
            return str(sa)
    return ""
