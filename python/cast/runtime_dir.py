"""The runtime directory of a running system: its secret, its address, the component logs.

``cast run`` writes, in the runtime directory (``--runtime-dir``, else
``$CAST_RUNTIME_DIR``, else ``.cast`` in the working directory):

- ``secret``: the token secret of this run (mode 0600), so that ``cast token``
  issues tokens the running system accepts (dynamic join) and the inspection
  commands can identify themselves;
- ``system.json``: ``{"system", "endpoint", "servers", "pid", "config"}``, so that
  tools find the running system without being told its address;
- ``logs/<component>.log``: each component's output.

``secret`` and ``system.json`` are removed on shutdown; the logs stay.

The orchestrator writes it; the client library (``cast.connect``, scripts) and the
CLI read it, so it lives beside them, not inside the orchestrator.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cast.errors import CastError

__all__ = ["RuntimeDir", "RuntimeDirBusyError", "default_runtime_dir"]


class RuntimeDirBusyError(CastError):
    """Another ``cast run`` is using the runtime directory."""

    code = "FAILED_PRECONDITION"


def default_runtime_dir(env: Mapping[str, str] | None = None) -> Path:
    """``$CAST_RUNTIME_DIR`` or ``.cast`` in the working directory."""
    env = os.environ if env is None else env
    return Path(env.get("CAST_RUNTIME_DIR") or ".cast")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True


@dataclass
class RuntimeDir:
    """The files through which a running system is found."""

    path: Path

    @property
    def secret_path(self) -> Path:
        """The token secret."""
        return self.path / "secret"

    @property
    def state_path(self) -> Path:
        """The running system's description."""
        return self.path / "system.json"

    @property
    def logs(self) -> Path:
        """The directory of component logs."""
        return self.path / "logs"

    def read_state(self) -> dict[str, Any] | None:
        """The description written by a running ``cast run``, or None (absent, or its process is gone)."""
        try:
            state = json.loads(self.state_path.read_text())
        except (OSError, ValueError):
            return None
        pid = int(state.get("pid", 0))
        if not pid or not _alive(pid):
            return None
        return dict(state)

    def read_secret(self) -> bytes | None:
        """The secret of the running system, or None."""
        try:
            return self.secret_path.read_bytes().strip() or None
        except OSError:
            return None

    def claim(self) -> None:
        """Refuse if another live ``cast run`` uses this directory."""
        other = self.read_state()
        if other is not None and int(other["pid"]) != os.getpid():
            raise RuntimeDirBusyError(
                f"another `cast run` (pid {other['pid']}, system '{other.get('system')}') uses {self.path}: "
                "stop it, or give this one its own --runtime-dir"
            )
        self.path.mkdir(parents=True, exist_ok=True)
        self.logs.mkdir(exist_ok=True)

    def new_secret(self) -> bytes:
        """Make and store a fresh secret for this run."""
        secret = secrets.token_urlsafe(32).encode()
        self.write_secret(secret)
        return secret

    def write_secret(self, secret: bytes) -> None:
        """Store the secret, readable by the owner only."""
        tmp = self.secret_path.with_suffix(".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(secret + b"\n")
        tmp.replace(self.secret_path)

    def write_state(self, state: Mapping[str, Any]) -> None:
        """Publish the running system's description."""
        tmp = self.state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps({**state, "pid": os.getpid()}, indent=2))
        tmp.replace(self.state_path)

    def release(self) -> None:
        """Remove the secret and the description (the logs stay)."""
        for path in (self.secret_path, self.state_path):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
