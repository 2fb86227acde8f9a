"""Helpers of the reliability suite: restartable `cast serve` processes, raw stubs, waiting."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
import yaml

from tests import conftest
from tests.conftest import ServerHandle
from tests.conftest import wait_for as wait_for  # re-exported: the reliability tests import it from here


def serve(
    config_path: Path, listen: str = "127.0.0.1:0", env: dict[str, str] | None = None, cwd: Path | None = None,
    extra: tuple[str, ...] = (),
) -> ServerHandle:
    """Start `cast serve CONFIG [EXTRA...]` in its own process group and wait for its `listening on` line."""
    return conftest.serve(config_path, listen, env, cwd, extra, own_session=True)


def kill9(handle: ServerHandle) -> None:
    """SIGKILL a server process and reap it."""
    if handle.process.poll() is None:
        os.kill(handle.process.pid, signal.SIGKILL)
    handle.process.wait(10)


# What other programs of a test run put in /dev/shm while this one runs (make test runs two at once):
# Fast DDS's shared-memory transport and its tracing (the ROS 2 tests), iceoryx2 and Zenoh (the bench's peers).
_OTHERS = ("fastdds_", "fastrtps_", "fast_datasharing", "sem.fastdds_", "sem.fastrtps_", "iox2", "sem.iox2",
           "lttng-ust-wait-")


def dev_shm() -> set[str]:
    """The files in /dev/shm, but those of other programs (:data:`_OTHERS`): what a shared-memory test checks."""
    return {name for name in os.listdir("/dev/shm") if not name.startswith(_OTHERS) and not name.endswith(".zenoh")}


def write_config(path: Path, config: dict[str, Any]) -> Path:
    """Write a configuration as YAML; return its path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def serve_tls(tmp: Path, pki: dict[str, Path], client_auth: bool = False) -> ServerHandle:
    """`cast serve` of a one-SA system with TLS on, from the files of ``certs.make_pki``."""
    config = write_config(tmp / "system.yaml", {
        "system": "tls",
        "subarchitectures": {"vision": {}},
        "tls": {"ca": str(pki["ca"]), "cert": str(pki["cert"]), "key": str(pki["key"]), "client_auth": client_auth},
    })
    return serve(config)


def metadata(handle: ServerHandle, component: str, sa: str, privileged: bool = False) -> tuple[tuple[str, str]]:
    """Call metadata with a valid token."""
    return (("authorization", f"Bearer {handle.token(component, sa, privileged)}"),)


@pytest.fixture
def servers() -> Iterator[list[ServerHandle]]:
    """A list the test appends its server handles to; every one is stopped at the end."""
    started: list[ServerHandle] = []
    yield started
    for handle in started:
        if handle.process.poll() is None:
            handle.stop()


def channel(endpoint: str) -> grpc.Channel:
    """A plaintext channel."""
    return grpc.insecure_channel(endpoint)
