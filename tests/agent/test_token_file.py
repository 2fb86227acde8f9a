"""Expiring tokens on another host: the agent keeps a component's token file on its own host; Renew rewrites it."""

from __future__ import annotations

import stat
from pathlib import Path

import grpc
import psutil
import pytest

from cast.auth import TokenSigner
from cast.core.records import Identity
from cast.v1 import agent_pb2, agent_pb2_grpc
from tests.agent.harness import AgentHandle, Attachment, launch_request, metadata, start_agent
from tests.conftest import SECRET, ServerHandle


def renew(agent: AgentHandle, component_id: str, token: str) -> None:
    agent_pb2_grpc.AgentStub(agent.channel()).Renew(
        agent_pb2.RenewRequest(system="agenttest", component_id=component_id, token=token), metadata=metadata(),
        timeout=30)


def test_token_file_is_written_on_the_agents_host_and_renewed(agent: AgentHandle, wm_server: ServerHandle) -> None:
    stub = agent_pb2_grpc.AgentStub(agent.channel())
    attach = Attachment(agent.channel())
    request = launch_request("sleeper", wm_server.endpoint, SECRET)
    # What an orchestrator's own host would have named: the agent must replace both with its host's.
    request.env["CAST_TOKEN_FILE"] = "/nonexistent/orchestrator/tokens/sleeper.token"
    request.env["CAST_TLS_CA"] = "/nonexistent/orchestrator/ca.pem"
    request.token_file = True
    reply = stub.Launch(request, metadata=metadata(), timeout=30)
    try:
        attach.wait(lambda: any(o.text == "sleeper started" for o in attach.of("output", "sleeper")),
                    what="sleeper's start() (it read its token file)")
        env = psutil.Process(reply.pid).environ()
        assert "CAST_TLS_CA" not in env  # the configuration has no tls: on this host
        path = Path(env["CAST_TOKEN_FILE"])
        assert not str(path).startswith("/nonexistent")
        assert path.read_text().strip() == request.env["CAST_TOKEN"]
        assert stat.S_IMODE(path.stat().st_mode) == 0o600 and stat.S_IMODE(path.parent.stat().st_mode) == 0o700
        fresh = TokenSigner(SECRET.encode()).issue(Identity("sleeper", "sa"), 60)
        renew(agent, "sleeper", fresh)
        assert path.read_text().strip() == fresh
    finally:
        stub.Stop(agent_pb2.StopRequest(system="agenttest", component_id="sleeper", timeout_ms=10_000),
                  metadata=metadata(), timeout=30)
        attach.close()
    assert not path.exists()  # no process reads it any more


def test_renew_refuses_what_it_cannot_renew(agent: AgentHandle, wm_server: ServerHandle) -> None:
    stub = agent_pb2_grpc.AgentStub(agent.channel())
    attach = Attachment(agent.channel())
    stub.Launch(launch_request("sleeper", wm_server.endpoint, SECRET), metadata=metadata(), timeout=30)
    try:
        with pytest.raises(grpc.RpcError) as caught:
            renew(agent, "sleeper", "a-token")
        assert caught.value.code() is grpc.StatusCode.FAILED_PRECONDITION
        assert "launched without token_file" in (caught.value.details() or "")
        with pytest.raises(grpc.RpcError) as caught:
            renew(agent, "nobody", "a-token")
        assert caught.value.code() is grpc.StatusCode.NOT_FOUND
        with pytest.raises(grpc.RpcError) as caught:
            renew(agent, "sleeper", "")
        assert caught.value.code() is grpc.StatusCode.INVALID_ARGUMENT
    finally:
        stub.Stop(agent_pb2.StopRequest(system="agenttest", component_id="sleeper", timeout_ms=10_000),
                  metadata=metadata(), timeout=30)
        attach.close()


def test_the_agent_leaves_no_token_directory_behind(root: Path, wm_server: ServerHandle, tmp_path: Path) -> None:
    idle = start_agent(root, tmpdir=tmp_path)
    idle.process.kill()  # SIGKILL: it cleans nothing up
    idle.process.wait(10)
    assert list(tmp_path.iterdir()) == []  # an agent that wrote no token made no directory for them
    agent = start_agent(root, tmpdir=tmp_path)
    try:
        stub = agent_pb2_grpc.AgentStub(agent.channel())
        attach = Attachment(agent.channel())
        request = launch_request("sleeper", wm_server.endpoint, SECRET)
        request.token_file = True
        reply = stub.Launch(request, metadata=metadata(), timeout=30)
        path = Path(psutil.Process(reply.pid).environ()["CAST_TOKEN_FILE"])
        assert path.is_relative_to(tmp_path) and path.exists()
        attach.close()
    finally:
        agent.stop()
    assert list(tmp_path.iterdir()) == []  # the stopped agent removed its token directory
