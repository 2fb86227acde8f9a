"""TLS for the tools: `cast ls/get/watch/components/tasks/token` reach a system that has TLS on."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from cast_testing_pb2 import Counter

import cast
from cast.client.credentials import ClientTls
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from tests.conftest import PYTHONPATH, SECRET, ServerHandle
from tests.orchestrator.conftest import CAST, COMPONENTS, start_cast_run, wait_for
from tests.orchestrator.conftest import write_config as write_orch_config  # puts the test components on python_path
from tests.reliability.conftest import serve_tls


def _tool(*args: str, env: dict[str, str] | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    base = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    return subprocess.run([CAST, *args], env={**base, "CAST_SECRET": SECRET, **(env or {})}, cwd=cwd,
                          capture_output=True, text=True, timeout=60)


def _write(handle: ServerHandle, tls: ClientTls, entry_id: str) -> int:
    writer = cast.UnmanagedComponent()
    writer._cast_bind(GrpcTransport(handle.endpoint, handle.token("writer", "vision"), Identity("writer", "vision"),
                                    5.0, tls))
    try:
        return writer.add(entry_id, Counter(value=5)).version
    finally:
        writer._cast_close()


def _ids(out: subprocess.CompletedProcess[str]) -> list[str]:
    assert out.returncode == 0, out.stderr
    return [e["id"] for e in json.loads(out.stdout)]


def test_tools_speak_tls_with_flags_or_the_launch_variables(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki)
    try:
        version = _write(handle, ClientTls(pki["ca"]), "seen")
        where = ("--endpoint", handle.endpoint)
        assert _ids(_tool("ls", "vision", *where, "--json", "--tls-ca", str(pki["ca"]))) == ["seen"]
        assert _ids(_tool("ls", "vision", *where, "--json", env={"CAST_TLS_CA": str(pki["ca"])})) == ["seen"]
        got = _tool("get", "vision", "seen", *where, "--json", "--tls-ca", str(pki["ca"]))
        assert got.returncode == 0 and json.loads(got.stdout)["version"] == version, got.stderr
        # Plaintext against a TLS server: refused, and the error says what to give.
        plain = _tool("ls", *where)
        assert plain.returncode != 0 and "--tls-ca" in plain.stderr and "plaintext" in plain.stderr, plain.stderr
        # Trusting the wrong CA: refused, naming the CA the tool trusted.
        wrong = _tool("ls", *where, "--tls-ca", str(pki["other_ca"]))
        assert wrong.returncode != 0 and str(pki["other_ca"]) in wrong.stderr, wrong.stderr
        # A half-given client certificate is a usage error, caught before any connection.
        half = _tool("ls", *where, "--tls-ca", str(pki["ca"]), "--tls-cert", str(pki["client_cert"]))
        assert half.returncode != 0 and "--tls-key" in half.stderr, half.stderr
    finally:
        handle.stop()


def test_tools_present_a_client_certificate_when_required(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki, client_auth=True)
    try:
        _write(handle, ClientTls(pki["ca"], pki["client_cert"], pki["client_key"]), "seen")
        where = ("--endpoint", handle.endpoint, "--tls-ca", str(pki["ca"]))
        without = _tool("ls", "vision", *where)
        assert without.returncode != 0 and "--tls-cert" in without.stderr, without.stderr
        with_cert = _tool("ls", "vision", *where, "--json", "--tls-cert", str(pki["client_cert"]),
                          "--tls-key", str(pki["client_key"]))
        assert _ids(with_cert) == ["seen"]
    finally:
        handle.stop()


def test_tools_find_the_tls_of_a_running_cast_run(tmp_path: Path, pki: dict[str, Path]) -> None:
    """`cast run` with TLS launches its components over TLS and records the CA, so tools need no flags."""
    config = write_orch_config(tmp_path / "system.yaml", {
        "system": "tls-run",
        "tls": {"ca": str(pki["ca"]), "cert": str(pki["cert"]), "key": str(pki["key"]), "client_auth": True,
                "client_cert": str(pki["client_cert"]), "client_key": str(pki["client_key"])},
        "subarchitectures": {"work": {"components": {
            "producer": {"class": "orch_components:Producer", "args": {"count": 2}},
        }}},
    })
    run = start_cast_run(tmp_path, config)
    try:
        assert run.state()["tls"] == {"ca": str(pki["ca"].resolve()), "cert": str(pki["client_cert"].resolve()),
                                      "key": str(pki["client_key"].resolve())}
        wait_for(lambda: len(run.cli_json("ls", "work")) == 2, what="the producer's items, written over TLS")
        assert [c["id"] for c in run.cli_json("components")] == ["producer"]
        watched = run.cli("watch", "--sa", "work", "--from", "1", "--count", "1")
        assert json.loads(watched.stdout.splitlines()[0])["id"] == "item-0"
        assert [c["subarchitecture"] for c in run.cli_json("tasks")["subarchitectures"]] == ["work"]
        exports = json.loads(run.cli("token", "late", "--sa", "work", "--json").stdout)
        assert exports["CAST_TLS_CA"] == str(pki["ca"].resolve())
        assert exports["CAST_TLS_CERT"] == str(pki["client_cert"].resolve())
        # A component started by hand with those exports reaches the TLS servers.
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        env.update(exports, PYTHONPATH=os.pathsep.join([str(COMPONENTS), PYTHONPATH]))
        late = subprocess.Popen([sys.executable, "-m", "cast.run", "orch_components:Joiner"], env=env)
        try:
            wait_for(lambda: any(e["id"] == "joined-late" for e in run.cli_json("ls", "work")), what="its entry")
        finally:
            late.terminate()
            assert late.wait(30) == 0
    finally:
        assert run.stop() == 0, run.output()
