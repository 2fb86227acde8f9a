"""The security part of the launch contract: expiring tokens renewed through files, and TLS settings.

With ``auth.token_ttl`` set, each launched component gets a token that expires
after that many seconds, in ``CAST_TOKEN`` and in the file ``CAST_TOKEN_FILE``
(``<runtime dir>/tokens/<component>.token``, mode 0600). The orchestrator
rewrites every file with a fresh token each ``ttl / 3`` seconds, atomically
(write, then rename); client libraries re-read the file when it changes and
send the newest token. A component the orchestrator no longer runs gets no new
token, so a leaked token stops working within ``ttl``. Without a ttl tokens
never expire and no file is written. A component on another host gets its file
from its agent, on that host (``LaunchRequest.token_file``); renewing it sends
the fresh token to the agent (``Agent.Renew``, through the ``remote`` hook).

With ``tls:`` in the configuration, components get ``CAST_TLS_CA`` (to verify
the servers) and, when servers require client certificates, ``CAST_TLS_CERT``
and ``CAST_TLS_KEY`` (``tls.client_cert``/``client_key``, else ``cert``/``key``).
A component on another host gets them from its agent, which resolves the same
``tls:`` entries on its own host (:func:`component_tls`): the paths are that
host's, and no key crosses the network.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Protocol

from cast.auth import TokenSigner, write_token_file
from cast.client.credentials import ClientTls
from cast.config.model import ComponentConfig, SystemConfig
from cast.core.records import Identity
from cast.errors import CastError

__all__ = ["LaunchSecurity", "RemoteRenewal", "Runs", "component_tls"]

log = logging.getLogger("cast.orchestrator")

RemoteRenewal = Callable[[ComponentConfig, str], Awaitable[None]]
"""Sends a remote component's fresh token to its agent (``Agents.renew``)."""


class Runs(Protocol):
    """Whether a component's process runs now; ``steady``: and no stop began (``Supervisor.runs``)."""

    def __call__(self, component_id: str, *, steady: bool = False) -> bool:
        """True while it runs."""


def component_tls(config: SystemConfig) -> ClientTls | None:
    """What launched components and tools use: the CA, and the client identity when servers require one."""
    tls = config.tls
    if tls is None:
        return None
    return ClientTls(tls.ca, *tls.component_identity) if tls.client_auth else ClientTls(tls.ca)


class LaunchSecurity:
    """Issues (and renews) the tokens and TLS variables of launched components."""

    def __init__(self, config: SystemConfig, signer: TokenSigner, runtime_dir: Path) -> None:
        self.config = config
        self.signer = signer
        self.ttl = config.auth.token_ttl
        self.token_dir = runtime_dir / "tokens"
        self._issued: dict[str, ComponentConfig] = {}
        self.renewals = 0
        self.remote: RemoteRenewal | None = None  # set when some components run on other hosts
        # One that exited gets no fresh token, so a token it leaked stops working within the ttl; one being
        # stopped still does, so that it can leave cleanly however long its stop takes.
        self.runs: Runs = lambda _component_id, steady=False: True

    def contract(self, comp: ComponentConfig) -> dict[str, str]:
        """``CAST_TOKEN`` (and ``CAST_TOKEN_FILE``, ``CAST_TLS_*`` on this host) for one component."""
        token = self._token(comp)
        env = {"CAST_TOKEN": token}
        if self.ttl:
            self._issued[comp.id] = comp
            if not comp.remote:  # its agent writes the file on its own host (token_file)
                env["CAST_TOKEN_FILE"] = str(self._write(comp.id, token))
        client = component_tls(self.config)
        if client is not None and not comp.remote:
            env |= client.env()
        return env

    def tls_state(self) -> dict[str, str] | None:
        """The TLS files a tool needs to reach the servers (CA, and client cert/key when required), or None."""
        client = component_tls(self.config)
        if client is None:
            return None
        state = {"ca": str(client.ca.resolve())}
        if client.cert is not None and client.key is not None:
            state |= {"cert": str(client.cert.resolve()), "key": str(client.key.resolve())}
        return state

    def _token(self, comp: ComponentConfig) -> str:
        return self.signer.issue(Identity(comp.id, comp.subarchitecture, comp.privileged), self.ttl)

    def _write(self, component_id: str, token: str) -> Path:
        path = self.token_dir / f"{component_id}.token"
        write_token_file(path, token)
        return path

    async def renew_all(self) -> None:
        """A fresh token for every running component issued one: into its file here, or to its agent."""
        for comp in list(self._issued.values()):
            if not self.runs(comp.id):
                continue  # a relaunch issues a fresh token through the contract
            token = self._token(comp)
            if not comp.remote:
                self._write(comp.id, token)
            elif self.remote is not None:
                try:
                    await self.remote(comp, token)
                except CastError as exc:
                    if not self.runs(comp.id, steady=True):
                        # It exited, or its stop began, while the call was under way: its agent may no longer
                        # know it, and nothing is left to renew.
                        log.debug("token of component '%s' not renewed: it ended meanwhile (%s)", comp.id, exc)
                        continue
                    # Its host is lost or it is restarting: a relaunch issues a fresh token anyway, and one
                    # unreachable host must not hold up the others' renewal.
                    log.warning("cannot renew the token of component '%s' on host '%s': %s", comp.id, comp.host,
                                exc)
        self.renewals += 1

    async def renew_forever(self) -> None:
        """Renew every ``ttl / 3`` seconds until cancelled (nothing to do without a ttl)."""
        if not self.ttl:
            return
        while True:
            await asyncio.sleep(max(0.2, self.ttl / 3))
            await self.renew_all()
