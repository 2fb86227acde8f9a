"""``cast serve CONFIG``: one server hosting every SA of a configuration (no components launched)."""

from __future__ import annotations

import argparse
import asyncio
import sys
import threading
import time
from typing import Any

from cast.auth import TokenSigner, load_or_create_secret
from cast.cli.options import parse_sets
from cast.config import load_config
from cast.config.model import ServerConfig, SystemConfig
from cast.errors import InvalidArgumentError, NotFoundError
from cast.signals import say

__all__ = ["add_commands"]


def _serve(args: argparse.Namespace) -> int:
    from cast.server.allocator import return_large_blocks
    from cast.server.app import RunningServer, serve_forever, settings_from_config, system_from_config
    from cast.server.in_process import InProcessComponents

    config = load_config(args.config, parse_sets(args.set))
    sys.path[:0] = [str(p) for p in config.python_path]  # in-process components import from there
    server = _chosen_server(config, args.server)
    system = system_from_config(config, lease_ms=args.lease_ms, server=server, metrics=not args.no_metrics,
                                shared_memory=not args.no_shared_memory)
    signer = TokenSigner(load_or_create_secret(args.secret_file))
    in_process = InProcessComponents(system)

    routes = _routes(args.route)
    endpoint = None
    if args.metrics:
        from cast.server.prometheus import serve_metrics

        # Bound before the server starts, so that a taken port stops it before anyone connects.
        endpoint = serve_metrics(args.metrics, system.metrics.snapshot)
    if args.await_run:
        # Held until the directory's barrier is released (a server `cast run` started on another host).
        system.barrier.hold()

    def started(running: RunningServer) -> None:
        running.routes.remote.update(routes)  # where the other servers' SAs are
        if args.await_run:
            threading.Thread(target=_await_run, args=(args.await_run, signer, system.barrier, config),
                             daemon=True, name="await-run").start()
        for comp in config.components:
            # With --server, only the in-process components of the SAs this server hosts.
            if comp.in_process and (server is None or comp.subarchitecture in server.subarchitectures):
                in_process.start(comp)
        running.on_stop(in_process.stop_all)
        if endpoint is not None:
            say(f"metrics on http://{endpoint.address}/metrics")  # after the listening line
            running.on_stop(endpoint.close)

    settings = settings_from_config(config)
    if args.exit_with_stdin:
        from cast.signals import terminate_when_stdin_closes

        terminate_when_stdin_closes()
    return_large_blocks()  # freed images go back to the system (cast.server.allocator)
    asyncio.run(serve_forever(system, signer, args.listen, started, settings))
    return 0


def _routes(given: list[str]) -> dict[str, str]:
    routes: dict[str, str] = {}
    for item in given:
        sa, sep, address = item.partition("=")
        if not sep or not sa or ":" not in address:
            raise InvalidArgumentError(f"--route {item!r}: write SA=HOST:PORT")
        routes[sa] = address
    return routes


def _await_run(directory: str, signer: TokenSigner, barrier: Any, config: SystemConfig) -> None:
    """Long-poll the directory's AwaitRun, then release this server's own barrier."""
    import grpc

    from cast.client.channel import ServerLink
    from cast.orchestrator.agent_link import orchestrator_metadata
    from cast.orchestrator.security import component_tls
    from cast.v1 import directory_pb2

    # In a TLS system the directory is dialled as a component would: its CA, and its client certificate
    # when the servers require one.
    link = ServerLink(directory, component_tls(config))
    metadata = orchestrator_metadata(signer)
    while not barrier.released:
        try:
            link.directory.AwaitRun(directory_pb2.AwaitRunRequest(), metadata=metadata, timeout=5.0)
        except grpc.RpcError as exc:
            if exc.code() not in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNAVAILABLE):
                say(f"await-run: {exc.code().name}: {exc.details()}", sys.stderr)
            time.sleep(0.2)
            continue
        barrier.release()
        say(f"start barrier released (by the directory at {directory})")
    link.close()


def _chosen_server(config: SystemConfig, name: str | None) -> ServerConfig | None:
    """The server of the configuration to serve; None serves every SA as one server."""
    names = [srv.name for srv in config.servers]
    if name is not None:
        found = next((srv for srv in config.servers if srv.name == name), None)
        if found is None:
            raise NotFoundError(f"no server '{name}' in {config.source} (servers: {', '.join(names)})")
        return found
    persistent = [srv.name for srv in config.servers if srv.persistence is not None]
    if len(config.servers) > 1 and persistent:
        # Serving every SA as one would drop each server's journal: refuse rather than lose writes.
        raise InvalidArgumentError(
            f"{config.source} has {len(names)} servers ({', '.join(names)}) and persistence on "
            f"{', '.join(persistent)}: give --server NAME to serve one of them with its persistence, "
            "or start the whole system with `cast run`"
        )
    return config.servers[0] if len(config.servers) == 1 else None


def add_commands(sub: Any) -> None:
    """Add ``cast serve``."""
    serve = sub.add_parser("serve", help="serve the working memories of a configuration (components not launched)")
    serve.add_argument("config", help="system configuration (YAML)")
    serve.add_argument("--listen", default="127.0.0.1:50051", help="HOST:PORT to listen on; port 0 picks a free one")
    serve.add_argument("--secret-file", help="token secret (default: $CAST_SECRET, else .cast/secret, created)")
    serve.add_argument("--lease-ms", type=int, default=10_000, help="session lease without heartbeats (ms)")
    serve.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a config variable")
    serve.add_argument("--server", help="serve only this server of the configuration's servers: section (its SAs "
                                        "and its persistence); default: every SA as one server")
    serve.add_argument("--route", action="append", default=[], metavar="SA=HOST:PORT",
                       help="where another server serves an SA (a server of a multi-server system)")
    serve.add_argument("--await-run", metavar="HOST:PORT",
                       help="hold the start barrier until the directory at HOST:PORT releases its own "
                            "(a server `cast run` starts on another host)")
    serve.add_argument("--metrics", metavar="HOST:PORT",
                       help="also serve the metrics in Prometheus's text format on http://HOST:PORT/metrics (port 0 "
                            "picks a free one; the address is printed after the listening line); docs/experiments.md")
    serve.add_argument("--no-metrics", action="store_true",
                       help="count nothing (the metrics are on by default; `cast stats` then shows zeros); for "
                            "measuring what counting costs")
    serve.add_argument("--exit-with-stdin", action="store_true",
                       help="stop, as on SIGTERM, when standard input ends: started with a pipe, the server stops "
                            "when the process that started it ends, however it ends (the test kits use it)")
    serve.add_argument("--no-shared-memory", action="store_true",
                       help="keep no shared memory: every value travels as bytes, also to clients on this host "
                            "(the configuration's shared_memory.enabled: false does the same; docs/client-protocol.md)")
    serve.set_defaults(fn=_serve, log_level="INFO")


