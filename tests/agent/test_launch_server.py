"""`Agent.Launch` with ``server``: `cast serve --server NAME` with the agent's own secret file."""

from __future__ import annotations

from pathlib import Path

import grpc
import pytest

from cast.v1 import agent_pb2, agent_pb2_grpc, directory_pb2, directory_pb2_grpc
from tests.agent.harness import SECRET, SYSTEM, AgentHandle, Attachment, metadata, orchestrator_token

SERVERS = f'''\
system: {SYSTEM}
servers:
  main: {{listen: "127.0.0.1:0", subarchitectures: [sa]}}
  far: {{listen: "127.0.0.1:0", subarchitectures: [sb]}}
subarchitectures:
  sa: {{}}
  sb: {{}}
'''


def test_launch_starts_a_server_that_verifies_tokens_with_the_agents_secret(agent: AgentHandle, root: Path) -> None:
    (root / "servers.yaml").write_text(SERVERS)
    stub = agent_pb2_grpc.AgentStub(agent.channel())
    attach = Attachment(agent.channel())
    try:
        attach.wait(lambda: attach.of("attached"), what="the attached event")
        request = agent_pb2.LaunchRequest(system=SYSTEM, config_path="servers.yaml", server="far",
                                          routes={"sa": "127.0.0.1:1"})
        reply = stub.Launch(request, metadata=metadata(), timeout=60)
        assert reply.endpoint.startswith("127.0.0.1:"), reply
        argv = list(reply.argv)
        assert argv[argv.index("--server") + 1] == "far"
        assert SECRET not in " ".join(reply.argv)  # the secret goes as the agent's file, never in the command line
        with grpc.insecure_channel(reply.endpoint) as channel:
            directory = directory_pb2_grpc.DirectoryStub(channel)
            described = directory.DescribeSystem(directory_pb2.DescribeSystemRequest(),
                                                 metadata=metadata(orchestrator_token()), timeout=10)
            assert {(s.name, s.endpoint) for s in described.subarchitectures} == {
                ("sb", reply.endpoint), ("sa", "127.0.0.1:1")}
            with pytest.raises(grpc.RpcError) as refused:  # a token of another secret is refused by the server
                directory.DescribeSystem(directory_pb2.DescribeSystemRequest(),
                                         metadata=metadata(orchestrator_token("another-secret-0123456789abcdef-0123456789")),
                                         timeout=10)
            assert refused.value.code() is grpc.StatusCode.UNAUTHENTICATED
        assert any(o.text.startswith("listening on") for o in attach.of("output", "server:far"))
        stopped = stub.Stop(agent_pb2.StopRequest(system=SYSTEM, component_id="server:far", timeout_ms=5000),
                            metadata=metadata(), timeout=30)
        assert stopped.exit.pid == reply.pid and not stopped.exit.killed

        with pytest.raises(grpc.RpcError) as unknown:
            stub.Launch(agent_pb2.LaunchRequest(system=SYSTEM, config_path="servers.yaml", server="nowhere"),
                        metadata=metadata(), timeout=30)
        assert unknown.value.code() is grpc.StatusCode.NOT_FOUND
        assert "no server 'nowhere'" in (unknown.value.details() or "")
    finally:
        attach.close()


def test_probe_says_whether_a_server_could_start_here(agent: AgentHandle, root: Path) -> None:
    (root / "servers.yaml").write_text(SERVERS)
    tls = SERVERS.replace("subarchitectures:\n  sa", "tls: {ca: certs/ca.pem, cert: certs/server.pem, "
                                                      "key: certs/server.key}\nsubarchitectures:\n  sa", 1)
    (root / "servers-tls.yaml").write_text(tls)
    stub = agent_pb2_grpc.AgentStub(agent.channel())
    reply = stub.Probe(agent_pb2.ProbeRequest(config_path="servers.yaml", component_ids=["server:far", "server:x"]),
                       metadata=metadata(), timeout=30)
    assert [(r.component_id, r.launchable) for r in reply.results] == [("server:far", True), ("server:x", False)]
    assert "no server 'x'" in reply.results[1].problem
    missing = stub.Probe(agent_pb2.ProbeRequest(config_path="servers-tls.yaml", component_ids=["server:far"]),
                         metadata=metadata(), timeout=30)
    assert not missing.results[0].launchable
    assert "TLS file" in missing.results[0].problem and "ca.pem" in missing.results[0].problem
