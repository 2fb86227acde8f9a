"""An orchestrator stand-in: attaches to an agent, launches one component, prints its pid, keeps the session alive.

    python -m tests.agent.standin AGENT_ENDPOINT SERVER_ENDPOINT SERVER_SECRET COMPONENT LEASE_MS

The test SIGKILLs it and checks that the agent stops the component after the lease.
"""

from __future__ import annotations

import sys
import time

import grpc

from cast.v1 import agent_pb2_grpc
from tests.agent.harness import Attachment, launch_request, metadata


def main() -> int:
    agent_endpoint, server_endpoint, server_secret, component_id, lease_ms = sys.argv[1:6]
    channel = grpc.insecure_channel(agent_endpoint)
    attach = Attachment(channel, lease_ms=int(lease_ms))
    attach.wait(lambda: attach.of("attached"), what="the attached event")
    reply = agent_pb2_grpc.AgentStub(channel).Launch(
        launch_request(component_id, server_endpoint, server_secret), metadata=metadata(), timeout=30)
    print(f"pid {reply.pid}", flush=True)
    while True:  # keepalives go out from the Attachment's thread until this process is killed
        time.sleep(1)


if __name__ == "__main__":
    sys.exit(main())
