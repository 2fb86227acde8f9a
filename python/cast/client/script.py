"""Working memories from a plain script, a test or a notebook: ``cast.connect``.

::

    with cast.connect() as wm:
        wm.add(wm.new_id(), StringValue(value="hello"))
        wm.on_change(cast.local_type_filter(StringValue), print)

A :class:`Connection` has every call of an unmanaged component (the same
names, errors and watches) and a live session, so it may lock; it has no
lifecycle hooks. Where it connects, and as whom, in this order:

- endpoint: ``endpoint=``, else ``$CAST_ENDPOINT``, else the running
  ``cast run``'s ``system.json`` in the runtime directory (``runtime_dir=``,
  else ``$CAST_RUNTIME_DIR``, else ``.cast``);
- identity: ``token=``, else the file ``$CAST_TOKEN_FILE`` (re-read when
  renewed), else ``$CAST_TOKEN`` (the launch environment), else a token made
  from the system's secret (``$CAST_SECRET``, ``$CAST_SECRET_FILE``, the
  runtime directory's ``secret``) for ``component_id=`` (default
  ``script-<host>-<pid>``) in ``subarchitecture=`` (default: the first SA
  the running system recorded), privileged: whoever holds the secret is
  trusted with every SA;
- TLS: ``tls=``, else ``$CAST_TLS_*``, else what ``cast run`` recorded.

The C++ (``cast::connect``) and Java (``Cast.connect``) libraries follow the
same rules.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType

from cast.auth import TokenSigner
from cast.client.component import UnmanagedComponent
from cast.client.credentials import ClientTls, TokenSource
from cast.client.discovery import find_endpoint, find_secret, find_tls, first_subarchitecture
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from cast.core.sessions import ComponentState
from cast.errors import InvalidArgumentError
from cast.runtime_dir import RuntimeDir, default_runtime_dir

__all__ = ["Connection", "connect"]


class Connection(UnmanagedComponent):
    """A session with a system's working memories, for code that is not a component; close it when done."""

    _closed = False

    def close(self) -> None:
        """End the session (its locks are released) and close the connection."""
        if not self._closed:
            self._closed = True
            self.request_stop()
            self._cast_close()

    def __enter__(self) -> Connection:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.close()


def connect(
    endpoint: str | None = None,
    token: str | None = None,
    *,
    component_id: str | None = None,
    subarchitecture: str | None = None,
    runtime_dir: str | os.PathLike[str] | None = None,
    tls: ClientTls | None = None,
    call_timeout: float = 30.0,
    env: Mapping[str, str] | None = None,
) -> Connection:
    """Connect to a running system (see the module docstring for where it looks); a :class:`Connection`."""
    env = os.environ if env is None else env
    runtime = RuntimeDir(Path(runtime_dir) if runtime_dir is not None else default_runtime_dir(env))
    address = find_endpoint(endpoint, runtime, env)
    tokens, told = _tokens(token, component_id, subarchitecture, runtime, env)
    if tls is None:
        tls = find_tls(None, runtime, env)
    connection = Connection()
    # The server's answer to Register completes (and checks) the identity: cast.client.session.
    connection._cast_bind(GrpcTransport(address, tokens, told, call_timeout, tls), language="python")
    connection._set_state(ComponentState.RUNNING)
    return connection


def _tokens(
    token: str | None, component_id: str | None, sa: str | None, runtime: RuntimeDir, env: Mapping[str, str]
) -> tuple[TokenSource, Identity]:
    """The token to send, and who the connection was told it is (empty parts: left to the token)."""
    if token:
        return TokenSource(token), Identity(component_id or "", sa or "", False)
    told = Identity(component_id or env.get("CAST_COMPONENT_ID", ""), sa or env.get("CAST_SUBARCHITECTURE", ""))
    if path := env.get("CAST_TOKEN_FILE"):
        return TokenSource.from_file(path), told
    if env.get("CAST_TOKEN"):
        return TokenSource(env["CAST_TOKEN"]), told
    secret = find_secret(None, runtime, env)
    sa = sa or first_subarchitecture(runtime)
    if not sa:
        raise InvalidArgumentError(
            "no subarchitecture for this connection: give subarchitecture= (no running `cast run` recorded its SAs "
            f"in {runtime.state_path})"
        )
    who = Identity(component_id or f"script-{socket.gethostname()}-{os.getpid()}", sa, True)
    return TokenSource(TokenSigner(secret).issue(who)), who
