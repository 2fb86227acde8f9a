"""TLS: a server with a certificate from the configuration; TLS clients work, plaintext is refused."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import grpc
import pytest
from cast_testing_pb2 import Counter

import cast
from cast.client.credentials import ClientTls, TokenSource
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from cast.v1 import directory_pb2, directory_pb2_grpc
from tests.conftest import PYTHONPATH, ServerHandle
from tests.reliability.conftest import serve_tls


def _connect(handle: ServerHandle, tls: ClientTls | None, component: str = "c") -> cast.UnmanagedComponent:
    identity = Identity(component, "vision")
    component_obj = cast.UnmanagedComponent()
    component_obj._cast_bind(GrpcTransport(handle.endpoint, handle.token(component, "vision"), identity, 5.0, tls))
    return component_obj


def _plaintext_status(handle: ServerHandle) -> grpc.StatusCode:
    channel = grpc.insecure_channel(handle.endpoint)
    try:
        directory_pb2_grpc.DirectoryStub(channel).DescribeSystem(
            directory_pb2.DescribeSystemRequest(),
            metadata=(("authorization", f"Bearer {handle.token('x', 'vision')}"),), timeout=5)
    except grpc.RpcError as exc:
        return exc.code()
    finally:
        channel.close()
    return grpc.StatusCode.OK


def test_tls_client_works_and_plaintext_is_refused(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki)
    try:
        c = _connect(handle, ClientTls(pki["ca"]))
        try:
            c.add("x", Counter(value=7))
            seen: list[int] = []
            c.on_change(cast.ChangeFilter(), lambda ch: seen.append(ch.revision))
            c.overwrite("x", Counter(value=8))
            assert c.get("x", Counter).value == 8
            assert c.drain(5)
        finally:
            c._cast_close()
        assert _plaintext_status(handle) == grpc.StatusCode.UNAVAILABLE
        # A client that trusts another CA does not accept the server's certificate.
        with pytest.raises(cast.UnavailableError):
            _connect(handle, ClientTls(pki["other_ca"]))
    finally:
        handle.stop()


def test_client_certificates_when_the_server_requires_them(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki, client_auth=True)
    try:
        with pytest.raises(cast.UnavailableError):
            _connect(handle, ClientTls(pki["ca"]))  # no client certificate
        c = _connect(handle, ClientTls(pki["ca"], pki["client_cert"], pki["client_key"]))
        c.add("y", Counter(value=1))
        c._cast_close()
    finally:
        handle.stop()


def test_a_component_process_uses_tls_from_the_launch_contract(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki)
    try:
        env = handle.env("writer", "vision", args={"count": 3})
        env.update(CAST_TLS_CA=str(pki["ca"]), PYTHONPATH=PYTHONPATH)
        done = subprocess.run([sys.executable, "-m", "cast.run", "itest_components:Writer"], env=env,
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stdout + done.stderr
        # Without the CA the same component cannot connect (and says so, after its connect window: 1 s here).
        env.pop("CAST_TLS_CA")
        env["CAST_CONNECT_WINDOW_S"] = "1"
        failed = subprocess.run([sys.executable, "-m", "cast.run", "itest_components:Writer"], env=env,
                                capture_output=True, text=True, timeout=60)
        assert failed.returncode == 2 and "within 1 s" in failed.stderr, failed.stderr
        reader = _connect(handle, ClientTls(pki["ca"]), "reader")
        try:
            assert len(reader.get_all(Counter)) == 2  # 3 written, one deleted
        finally:
            reader._cast_close()
    finally:
        handle.stop()


def test_launch_contract_tls_variables_are_checked() -> None:
    assert ClientTls.from_env({}) is None
    with pytest.raises(cast.InvalidArgumentError, match="CAST_TLS_CA"):
        ClientTls.from_env({"CAST_TLS_CERT": "c.pem", "CAST_TLS_KEY": "k.pem"})
    with pytest.raises(cast.InvalidArgumentError, match="both"):
        ClientTls.from_env({"CAST_TLS_CA": "ca.pem", "CAST_TLS_CERT": "c.pem"})
    tls = ClientTls.from_env({"CAST_TLS_CA": "ca.pem", "CAST_TLS_SERVER_NAME": "wm.example"})
    assert tls is not None and tls.channel_options() == [("grpc.ssl_target_name_override", "wm.example")]


def test_token_source_rereads_a_renewed_file(tmp_path: Path) -> None:
    path = tmp_path / "token"
    path.write_text("first\n")
    source = TokenSource("initial", path, check_interval=0)
    assert source.token() == "first"
    path.write_text("second-and-longer\n")
    assert source.token() == "second-and-longer"
    path.write_text("")  # being replaced: keep the last good token
    assert source.token() == "second-and-longer"
    os.unlink(path)
    assert source.token() == "second-and-longer"
