"""The Python client's C modules for the tests that hold them to the pure path.

The compiled build (make mypyc) has them installed, and there they are what is
tested (`make test` runs these tests against it); an editable checkout has
none, so they are built here from their sources with the C compiler, and the C
code is what is tested either way.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import socket
import subprocess
import sysconfig
from pathlib import Path
from types import ModuleType

import pytest

from cast.client.shm_session import ClientSession
from cast.wire import shared_memory as wire

ROOT = Path(__file__).resolve().parents[2]
INSTALLED = os.environ.get("CAST_TEST_INSTALLED") == "1"
"""Whether the tests run against the installed compiled build (make test-mypyc)."""


def native_module(name: str, tmp_path_factory: pytest.TempPathFactory) -> tuple[ModuleType, bool]:
    """``cast.client.<name>`` (``_events_native``, say) and whether it is the build's own, else built from its source.

    The source is ``python/cast/client/<name without its underscore>.c``.
    """
    try:
        return importlib.import_module(f"cast.client.{name}"), True
    except ImportError:
        assert not INSTALLED, f"the compiled build (make mypyc) has no cast.client.{name}"
    source = ROOT / "python" / "cast" / "client" / f"{name.lstrip('_')}.c"
    out = tmp_path_factory.mktemp("native") / f"{name}{sysconfig.get_config_var('EXT_SUFFIX')}"
    subprocess.run(
        ["gcc", "-O2", "-Wall", "-Wextra", "-Werror", "-shared", "-fPIC", f"-I{sysconfig.get_paths()['include']}",
         str(source), "-o", str(out)],
        check=True,
    )
    spec = importlib.util.spec_from_file_location(f"cast.client.{name}", out)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module, False


def session_on_a_pair() -> tuple[socket.socket, ClientSession]:
    """A real client session (after its WELCOME) on one end of a Unix socket pair, and the server's end.

    The session is made with the ``_native`` and ``_receive`` modules
    :mod:`cast.client.shm_session` holds at the time: a test sets them first.
    """
    server, client = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    client.setblocking(False)
    staging = os.memfd_create("staging")
    os.ftruncate(staging, 1 << 16)
    body = wire.welcome(b"s" * 16, b"v" * 16, 1 << 10, 1 << 20, 1 << 16)[5:]
    return server, ClientSession(client, body, staging, "test", "token")

