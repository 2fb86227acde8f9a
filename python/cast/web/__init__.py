"""The web view: a running system in the browser (``cast web``, ``cast run --web``; docs/web.md).

One page with three views, fed live by server-sent events: the architecture
(SAs with their components, arrows weighted by the cross-SA traffic, rates
over the last minute), the working memories (entries, a value as JSON as it
changes, the last changes) and the task managers. The data comes from the
servers' public gRPC API under a reader identity (:mod:`cast.web.source`),
never from inside a server; the page needs a one-time login link or a token
the system accepts (:mod:`cast.web.access`). Beside the other tools in the
layering: the client library, the core's plain data helpers and the server's
wire translation of the metrics, never the orchestrator, the configuration,
the agent or the command line.
"""
