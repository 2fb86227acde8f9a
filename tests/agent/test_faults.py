"""The agent's half of the faults across hosts: a SIGKILLed orchestrator, a cut link, a SIGKILLed agent.

Tests never assert wall-clock times: each waits within a generous guard timeout and prints what it
measured (for the fault table of docs/multihost.md, "Faults across hosts").
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest

from cast.v1 import agent_pb2, agent_pb2_grpc
from tests.agent.harness import ROOT, AgentHandle, Attachment, launch_request, metadata, start_agent
from tests.conftest import SECRET, ServerHandle

GUARD_S = 30.0


def gone(pid: int) -> bool:
    """Whether ``pid`` is dead (reaped, or a zombie waiting for whoever adopted it)."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def wait_gone(pid: int, what: str) -> float:
    """Seconds until ``pid`` is dead; fails after the guard timeout."""
    started = time.monotonic()
    while not gone(pid):
        if time.monotonic() - started > GUARD_S:
            os.kill(pid, signal.SIGKILL)
            raise AssertionError(f"{what}: pid {pid} still runs after {GUARD_S} s")
        time.sleep(0.01)
    return time.monotonic() - started


@pytest.fixture
def own_agent(root: Path) -> Iterator[AgentHandle]:
    """An agent of this test alone (some tests kill it)."""
    handle = start_agent(root)
    yield handle
    handle.stop()


def test_the_agent_stops_a_dead_orchestrators_processes_after_the_lease(
    own_agent: AgentHandle, wm_server: ServerHandle
) -> None:
    lease_ms = 1500
    standin = subprocess.Popen(
        [sys.executable, "-m", "tests.agent.standin", own_agent.endpoint, wm_server.endpoint, SECRET, "sleeper",
         str(lease_ms)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert standin.stdout is not None
    first = standin.stdout.readline().strip()
    assert first.startswith("pid "), first
    pid = int(first.split()[1])
    time.sleep(lease_ms / 1000 * 1.5)  # longer than the lease: keepalives alone keep it running
    assert not gone(pid), "the component stopped while its orchestrator was alive"
    standin.kill()
    standin.wait()
    took = wait_gone(pid, "the orphan of a SIGKILLed orchestrator")
    print(f"\norchestrator SIGKILLed: the agent stopped its process {took:.2f} s later (lease {lease_ms} ms, "
          "grace 1000 ms)")
    assert any("lease expired" in line for line in own_agent.output), own_agent.output


def test_attaching_again_within_the_lease_keeps_the_process(own_agent: AgentHandle, wm_server: ServerHandle) -> None:
    lease_ms = 1000
    first = Attachment(own_agent.channel(), lease_ms=lease_ms)
    stub = agent_pb2_grpc.AgentStub(own_agent.channel())
    reply = stub.Launch(launch_request("sleeper", wm_server.endpoint, SECRET), metadata=metadata(), timeout=30)
    first.wait(lambda: any(o.text == "sleeper started" for o in first.of("output", "sleeper")), what="start()")
    first.cancel()  # the link is cut
    time.sleep(lease_ms / 1000 / 3)
    second = Attachment(own_agent.channel(), lease_ms=lease_ms, ack_seq=first.last_seq)
    attached = second.wait(lambda: second.of("attached"), what="the attached event")[0]
    assert attached.resumed and [(p.component_id, p.pid) for p in attached.running] == [("sleeper", reply.pid)]
    time.sleep(3 * lease_ms / 1000)  # three leases with keepalives on the new stream
    assert not gone(reply.pid)
    assert not any(o.text == "sleeper started" for o in second.of("output")), "acknowledged events came again"
    stub.Stop(agent_pb2.StopRequest(system="agenttest", component_id="sleeper"), metadata=metadata(), timeout=30)
    exit_ = second.wait(lambda: second.of("exit", "sleeper"), what="the exit on the new stream")[0]
    assert (exit_.pid, exit_.reason) == (reply.pid, "stopped")
    second.close()


def test_a_sigkilled_agents_processes_die_with_it(own_agent: AgentHandle, wm_server: ServerHandle) -> None:
    attach = Attachment(own_agent.channel(), lease_ms=60_000)
    stub = agent_pb2_grpc.AgentStub(own_agent.channel())
    reply = stub.Launch(launch_request("sleeper", wm_server.endpoint, SECRET), metadata=metadata(), timeout=30)
    attach.wait(lambda: any(o.text == "sleeper started" for o in attach.of("output", "sleeper")), what="start()")
    own_agent.process.kill()
    own_agent.process.wait()
    took = wait_gone(reply.pid, "the process of a SIGKILLed agent")
    print(f"\nagent SIGKILLed: its process died {took:.2f} s later (PR_SET_PDEATHSIG)")
