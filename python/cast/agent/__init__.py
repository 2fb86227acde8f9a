"""``cast agent``: the per-host daemon that runs component processes for an orchestrator elsewhere.

One agent runs on each host of a multi-host system (docs/multihost.md). It
serves ``cast.v1.Agent`` (``proto/cast/v1/agent.proto``): an orchestrator
attaches for its system, launches components (built with the same launchers
as ``cast run``, from the same checkout under the agent's ``--root``), gets
their output, exits and resource use as a stream, and stops them. If the
orchestrator goes away and does not come back within its lease, the agent
stops that system's processes.

Modules: ``app`` (the gRPC server), ``service`` (the servicer), ``processes``
(the process table and the lease reaper), ``sessions`` (one system's lease and
event buffer), ``launch`` (what to start, from the configuration), ``trust``
(mutual TLS and tokens), ``resources`` (CPU and RSS from /proc). The
orchestrator never imports this package: it talks to agents through the
generated ``cast.v1.agent_pb2_grpc`` stubs.
"""
