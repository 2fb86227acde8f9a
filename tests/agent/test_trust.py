"""Whom an agent obeys: without trust it does not start; a wrong or missing token, a non-orchestrator
identity, a TLS client without a certificate, or one signed by another CA start nothing."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import grpc
import psutil
import pytest

from cast.v1 import agent_pb2, agent_pb2_grpc
from tests.agent.harness import (
    CONFIG,
    VENV_BIN,
    AgentHandle,
    launch_request,
    metadata,
    orchestrator_token,
    start_agent,
)
from tests.conftest import SECRET, ServerHandle
from tests.reliability.certs import make_pki


def children(agent: AgentHandle) -> set[int]:
    return {p.pid for p in psutil.Process(agent.process.pid).children(recursive=True)}


def test_an_agent_without_trust_refuses_to_start(root: Path) -> None:
    result = subprocess.run([str(VENV_BIN / "cast"), "agent", "--listen", "127.0.0.1:0", "--root", str(root)],
                            capture_output=True, text=True, timeout=60,
                            env={k: v for k, v in os.environ.items() if not k.startswith("CAST_")})
    assert result.returncode == 2
    assert "--tls-ca" in result.stderr and "--secret-file" in result.stderr, result.stderr


@pytest.mark.parametrize("token", [
    None,
    orchestrator_token(secret="another-systems-secret-0123456789abcdef"),
    orchestrator_token(component_id="segmenter"),
    orchestrator_token(privileged=False),
    "not-a-jwt",
])
def test_a_wrong_or_missing_token_is_unauthenticated_and_starts_nothing(
    agent: AgentHandle, wm_server: ServerHandle, token: str | None
) -> None:
    stub = agent_pb2_grpc.AgentStub(agent.channel())
    call_metadata = metadata(token) if token is not None else ()
    before = children(agent)
    calls = {
        "Launch": lambda: stub.Launch(launch_request("sleeper", wm_server.endpoint, SECRET), metadata=call_metadata,
                                      timeout=10),
        "Probe": lambda: stub.Probe(agent_pb2.ProbeRequest(config_path=CONFIG), metadata=call_metadata, timeout=10),
        "Stop": lambda: stub.Stop(agent_pb2.StopRequest(system="agenttest", component_id="sleeper"),
                                  metadata=call_metadata, timeout=10),
        "Attach": lambda: list(stub.Attach(iter([agent_pb2.AttachRequest(system="agenttest")]),
                                           metadata=call_metadata, timeout=10)),
    }
    for name, call in calls.items():
        with pytest.raises(grpc.RpcError) as caught:
            call()
        assert caught.value.code() == grpc.StatusCode.UNAUTHENTICATED, (name, caught.value.details())
    assert children(agent) <= before


@pytest.fixture(scope="module")
def tls_agent(root: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AgentHandle, dict[str, Path]]]:
    """An agent trusting mutual TLS only (no secret file)."""
    pki = make_pki(tmp_path_factory.mktemp("pki"))
    handle = start_agent(root, "--tls-cert", str(pki["cert"]), "--tls-key", str(pki["key"]),
                         "--tls-ca", str(pki["ca"]), secret=False)
    yield handle, pki
    handle.stop()


def test_mutual_tls_admits_a_client_certificate_of_its_ca(tls_agent: tuple[AgentHandle, dict[str, Path]]) -> None:
    agent, pki = tls_agent
    assert "mutual TLS" in agent.first_line and "secret" not in agent.first_line
    credentials = grpc.ssl_channel_credentials(pki["ca"].read_bytes(), pki["client_key"].read_bytes(),
                                               pki["client_cert"].read_bytes())
    reply = agent_pb2_grpc.AgentStub(agent.channel(credentials)).Probe(
        agent_pb2.ProbeRequest(config_path=CONFIG, component_ids=["chatty"]), timeout=10)
    assert reply.results[0].launchable


def test_mutual_tls_refuses_a_client_without_a_certificate_of_its_ca(
    tls_agent: tuple[AgentHandle, dict[str, Path]], wm_server: ServerHandle
) -> None:
    agent, pki = tls_agent
    before = children(agent)
    other = make_pki(pki["ca"].parent.parent / "other-pki")  # a client certificate of another CA
    for credentials in (
        grpc.ssl_channel_credentials(pki["ca"].read_bytes()),
        grpc.ssl_channel_credentials(pki["ca"].read_bytes(), other["client_key"].read_bytes(),
                                     other["client_cert"].read_bytes()),
    ):
        stub = agent_pb2_grpc.AgentStub(agent.channel(credentials))
        with pytest.raises(grpc.RpcError) as caught:
            stub.Launch(launch_request("sleeper", wm_server.endpoint, SECRET), timeout=10)
        # The TLS handshake itself fails: no call reaches the agent. gRPC reports a failed handshake as
        # UNAVAILABLE (Python's grpc cannot ask for a certificate without requiring it, so the agent
        # cannot answer UNAUTHENTICATED instead); either way nothing starts.
        assert caught.value.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.UNAUTHENTICATED), (
            caught.value.details())
    assert children(agent) <= before
