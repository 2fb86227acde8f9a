"""`cast agent`: Launch, Attach events, Stop, Probe, health and reflection against a real agent process."""

from __future__ import annotations

import re

import grpc
import psutil
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from cast.v1 import agent_pb2, agent_pb2_grpc
from tests.agent.harness import CONFIG, AgentHandle, Attachment, launch_request, metadata
from tests.conftest import SECRET, ServerHandle


def stub(agent: AgentHandle) -> agent_pb2_grpc.AgentStub:
    return agent_pb2_grpc.AgentStub(agent.channel())


def test_the_first_line_says_where_and_how_it_trusts(agent: AgentHandle) -> None:
    assert agent.first_line.startswith("cast agent listening on 127.0.0.1:")
    assert "tokens signed with the secret in" in agent.first_line


def test_launch_streams_output_lines_and_the_exit(agent: AgentHandle, wm_server: ServerHandle) -> None:
    attach = Attachment(agent.channel())
    attach.wait(lambda: attach.of("attached"), what="the attached event")
    reply = stub(agent).Launch(launch_request("chatty", wm_server.endpoint, SECRET), metadata=metadata(), timeout=30)
    assert reply.pid > 0 and "agent_components:Chatty" in reply.argv
    exit_ = attach.wait(lambda: attach.of("exit", "chatty"), what="chatty's exit")[0]
    assert (exit_.pid, exit_.exit_code, exit_.signal, exit_.reason) == (reply.pid, 0, 0, "exited")
    lines = [o.text for o in attach.of("output", "chatty")]
    assert [line for line in lines if line.startswith("chatty")] == [
        "chatty line 0", "chatty line 1", "chatty line 2", "chatty on stderr"]
    attach.close()


def test_resource_samples_arrive_with_a_plausible_rss(agent: AgentHandle, wm_server: ServerHandle) -> None:
    attach = Attachment(agent.channel())
    reply = stub(agent).Launch(launch_request("sleeper", wm_server.endpoint, SECRET), metadata=metadata(), timeout=30)
    try:
        samples = attach.wait(lambda: [s for s in attach.of("resources", "sleeper") if s.rss_bytes][:2],
                              what="two resource samples")
        rss = psutil.Process(reply.pid).memory_info().rss
        print(f"\nsleeper rss: sampled {samples[-1].rss_bytes} bytes, psutil {rss} bytes; "
              f"cpu {samples[-1].cpu_percent:.1f} %")
        assert all(s.pid == reply.pid for s in samples)
        assert 5 * 2**20 < samples[-1].rss_bytes < 2 * 2**30
        assert 0.2 < samples[-1].rss_bytes / rss < 5
        assert all(s.cpu_percent >= 0 for s in samples)
    finally:
        stub(agent).Stop(agent_pb2.StopRequest(system="agenttest", component_id="sleeper", timeout_ms=10_000),
                         metadata=metadata(), timeout=30)
        attach.close()


def test_stop_ends_a_component_with_sigterm(agent: AgentHandle, wm_server: ServerHandle) -> None:
    attach = Attachment(agent.channel())
    reply = stub(agent).Launch(launch_request("sleeper", wm_server.endpoint, SECRET), metadata=metadata(), timeout=30)
    attach.wait(lambda: any(o.text == "sleeper started" for o in attach.of("output", "sleeper")), what="start()")
    stopped = stub(agent).Stop(agent_pb2.StopRequest(system="agenttest", component_id="sleeper", timeout_ms=10_000),
                               metadata=metadata(), timeout=30)
    assert (stopped.exit.pid, stopped.exit.exit_code, stopped.exit.killed, stopped.exit.reason) == (
        reply.pid, 0, False, "stopped")
    assert not psutil.pid_exists(reply.pid) or psutil.Process(reply.pid).status() == psutil.STATUS_ZOMBIE
    exit_ = attach.wait(lambda: attach.of("exit", "sleeper"), what="the exit event")[-1]
    assert exit_.reason == "stopped"
    attach.close()


def test_stop_kills_a_component_whose_stop_hangs(agent: AgentHandle, wm_server: ServerHandle) -> None:
    attach = Attachment(agent.channel())
    reply = stub(agent).Launch(launch_request("stubborn", wm_server.endpoint, SECRET), metadata=metadata(),
                               timeout=30)
    attach.wait(lambda: any(o.text == "stubborn started" for o in attach.of("output", "stubborn")), what="start()")
    stopped = stub(agent).Stop(agent_pb2.StopRequest(system="agenttest", component_id="stubborn", timeout_ms=500),
                               metadata=metadata(), timeout=30)
    assert (stopped.exit.pid, stopped.exit.signal, stopped.exit.killed) == (reply.pid, 9, True)
    # Asked with SIGQUIT before the SIGKILL, the runner printed its threads' stacks: where stop() hangs.
    attach.wait(lambda: [o for o in attach.of("output", "stubborn") if re.search(r'", line \d+ in stop$', o.text)],
                what="the stack of the thread in stop()")
    assert any(o.text.startswith("Thread 0x") for o in attach.of("output", "stubborn"))
    attach.close()


def test_a_bad_launch_names_the_problem_and_starts_nothing(agent: AgentHandle, wm_server: ServerHandle) -> None:
    attach = Attachment(agent.channel())
    attach.wait(lambda: attach.of("attached"), what="the attached event")
    before = {p.pid for p in psutil.Process(agent.process.pid).children(recursive=True)}
    cases = {
        "nobody": (grpc.StatusCode.NOT_FOUND, "no component 'nobody'"),
        "ghost": (grpc.StatusCode.NOT_FOUND, "module 'no_such_module' is not found on this host"),
        "native": (grpc.StatusCode.NOT_FOUND, "make cpp"),
    }
    for component_id, (code, text) in cases.items():
        with pytest.raises(grpc.RpcError) as caught:
            stub(agent).Launch(launch_request(component_id, wm_server.endpoint, SECRET), metadata=metadata(),
                               timeout=30)
        assert caught.value.code() == code, caught.value.details()
        assert text in (caught.value.details() or ""), caught.value.details()
    outside = launch_request("chatty", wm_server.endpoint, SECRET, config="../elsewhere.yaml")
    with pytest.raises(grpc.RpcError) as caught:
        stub(agent).Launch(outside, metadata=metadata(), timeout=30)
    assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "leaves" in (caught.value.details() or "")
    secret_env = launch_request("chatty", wm_server.endpoint, SECRET)
    secret_env.env["CAST_SECRET"] = "x" * 40
    with pytest.raises(grpc.RpcError) as caught:
        stub(agent).Launch(secret_env, metadata=metadata(), timeout=30)
    assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "CAST_SECRET" in (caught.value.details() or "")
    unattached = launch_request("chatty", wm_server.endpoint, SECRET, system="never-attached")
    with pytest.raises(grpc.RpcError) as caught:
        stub(agent).Launch(unattached, metadata=metadata(), timeout=30)
    assert caught.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "Attach first" in (
        caught.value.details() or "")
    after = {p.pid for p in psutil.Process(agent.process.pid).children(recursive=True)}
    assert after <= before
    attach.close()


def test_probe_reports_a_missing_module_and_a_missing_executable(agent: AgentHandle) -> None:
    reply = stub(agent).Probe(agent_pb2.ProbeRequest(config_path=CONFIG), metadata=metadata(), timeout=30)
    results = {r.component_id: r for r in reply.results}
    assert [r.component_id for r in reply.results] == ["chatty", "sleeper", "stubborn", "ghost", "native"]
    assert results["chatty"].launchable and not results["chatty"].problem
    assert not results["ghost"].launchable and "module 'no_such_module'" in results["ghost"].problem
    assert not results["native"].launchable and "not-built" in results["native"].problem
    one = stub(agent).Probe(agent_pb2.ProbeRequest(config_path=CONFIG, component_ids=["nobody"]),
                            metadata=metadata(), timeout=30)
    assert not one.results[0].launchable and "no component 'nobody'" in one.results[0].problem


def test_health_and_reflection_list_the_agent_service(agent: AgentHandle) -> None:
    channel = agent.channel()
    health = health_pb2_grpc.HealthStub(channel)
    for service in ("", "cast.v1.Agent"):
        answer = health.Check(health_pb2.HealthCheckRequest(service=service), timeout=10)
        assert answer.status == health_pb2.HealthCheckResponse.SERVING
    request = reflection_pb2.ServerReflectionRequest(list_services="")
    responses = reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo(
        iter([request]), metadata=metadata(), timeout=10)
    names = {s.name for r in responses for s in r.list_services_response.service}
    assert {"cast.v1.Agent", "grpc.health.v1.Health"} <= names


def test_a_new_session_ignores_the_ack_of_an_old_one(agent: AgentHandle, wm_server: ServerHandle) -> None:
    # An orchestrator re-attaching after the agent restarted still holds the old session's last seq:
    # the new session's events, numbered from 1 again, must reach it all the same.
    attach = Attachment(agent.channel(), system="fresh-session", ack_seq=1000)
    attached = attach.wait(lambda: attach.of("attached"), what="the attached event")[0]
    assert not attached.resumed
    request = launch_request("chatty", wm_server.endpoint, SECRET, system="fresh-session")
    stub(agent).Launch(request, metadata=metadata(), timeout=30)
    attach.wait(lambda: attach.of("exit", "chatty"), what="chatty's exit, although acked 1000 before")
    attach.close()
