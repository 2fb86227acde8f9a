"""The security part of the launch contract: expiring tokens renewed through files, and TLS settings.

With ``auth.token_ttl`` set, each launched component gets a token that expires
after that many seconds, in ``CAST_TOKEN`` and in the file ``CAST_TOKEN_FILE``
(``<runtime dir>/tokens/<component>.token``, mode 0600). The orchestrator
rewrites every file with a fresh token each ``ttl / 3`` seconds, atomically
(write, then rename); client libraries re-read the file when it changes and
send the newest token. A component the orchestrator no longer runs gets no new
token, so a leaked token stops working within ``ttl``. Without a ttl tokens
never expire and no file is written.

With ``tls:`` in the configuration, components get ``CAST_TLS_CA`` (to verify
the servers) and, when servers require client certificates, ``CAST_TLS_CERT``
and ``CAST_TLS_KEY`` (``tls.client_cert``/``client_key``, else ``cert``/``key``).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from pathlib import Path

from cast.auth import TokenSigner
from cast.client.credentials import ClientTls
from cast.config.model import ComponentConfig, SystemConfig
from cast.core.records import Identity

__all__ = ["LaunchSecurity"]


class LaunchSecurity:
    """Issues (and renews) the tokens and TLS variables of launched components."""

    def __init__(self, config: SystemConfig, signer: TokenSigner, runtime_dir: Path) -> None:
        self.config = config
        self.signer = signer
        self.ttl = config.auth.token_ttl
        self.token_dir = runtime_dir / "tokens"
        self._issued: dict[str, ComponentConfig] = {}
        self.renewals = 0

    def contract(self, comp: ComponentConfig) -> dict[str, str]:
        """``CAST_TOKEN`` (and ``CAST_TOKEN_FILE``, ``CAST_TLS_*``) for one component."""
        token = self._token(comp)
        env = {"CAST_TOKEN": token}
        if self.ttl:
            env["CAST_TOKEN_FILE"] = str(self._write(comp.id, token))
            self._issued[comp.id] = comp
        client = self._client_tls()
        if client is not None:
            env |= client.env()
        return env

    def _client_tls(self) -> ClientTls | None:
        """What launched components and tools use: the CA, and the client identity when servers require one."""
        tls = self.config.tls
        if tls is None:
            return None
        return ClientTls(tls.ca, *tls.component_identity) if tls.client_auth else ClientTls(tls.ca)

    def tls_state(self) -> dict[str, str] | None:
        """The TLS files a tool needs to reach the servers (CA, and client cert/key when required), or None."""
        client = self._client_tls()
        if client is None:
            return None
        state = {"ca": str(client.ca.resolve())}
        if client.cert is not None and client.key is not None:
            state |= {"cert": str(client.cert.resolve()), "key": str(client.key.resolve())}
        return state

    def forget(self, component_id: str) -> None:
        """Stop renewing a component's token (it was removed or stopped for good)."""
        self._issued.pop(component_id, None)

    def _token(self, comp: ComponentConfig) -> str:
        return self.signer.issue(Identity(comp.id, comp.subarchitecture, comp.privileged), self.ttl)

    def _write(self, component_id: str, token: str) -> Path:
        self.token_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        path = self.token_dir / f"{component_id}.token"
        tmp = path.with_suffix(".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(token + "\n")
        tmp.replace(path)  # readers see the old token or the new one, never half a file
        return path

    def renew_all(self) -> None:
        """Write a fresh token for every component issued one."""
        for comp in list(self._issued.values()):
            self._write(comp.id, self._token(comp))
        self.renewals += 1

    async def renew_forever(self) -> None:
        """Renew every ``ttl / 3`` seconds until cancelled (nothing to do without a ttl)."""
        if not self.ttl:
            return
        while True:
            await asyncio.sleep(max(0.2, self.ttl / 3))
            self.renew_all()
