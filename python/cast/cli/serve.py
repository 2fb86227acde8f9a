"""``cast serve CONFIG``: one server hosting every SA of a configuration (no components launched)."""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import Any

from cast.auth import TokenSigner, load_or_create_secret
from cast.cli.options import parse_sets
from cast.config import load_config
from cast.config.model import ServerConfig, SystemConfig
from cast.errors import InvalidArgumentError, NotFoundError

__all__ = ["add_command"]


def _serve(args: argparse.Namespace) -> int:
    from cast.server.app import RunningServer, serve_forever, settings_from_config, system_from_config
    from cast.server.in_process import InProcessComponents

    config = load_config(args.config, parse_sets(args.set))
    sys.path[:0] = [str(p) for p in config.python_path]  # in-process components import from there
    server = _chosen_server(config, args.server)
    system = system_from_config(config, lease_ms=args.lease_ms, server=server)
    signer = TokenSigner(load_or_create_secret(args.secret_file))
    in_process = InProcessComponents(system)

    def started(running: RunningServer) -> None:
        for comp in config.components:
            if comp.in_process:
                in_process.start(comp)
        running.on_stop(in_process.stop_all)

    asyncio.run(serve_forever(system, signer, args.listen, started, settings_from_config(config)))
    return 0


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


def add_command(sub: Any) -> None:
    """Add ``cast serve``."""
    serve = sub.add_parser("serve", help="serve the working memories of a configuration (components not launched)")
    serve.add_argument("config", help="system configuration (YAML)")
    serve.add_argument("--listen", default="127.0.0.1:50051", help="HOST:PORT to listen on; port 0 picks a free one")
    serve.add_argument("--secret-file", help="token secret (default: $CAST_SECRET, else .cast/secret, created)")
    serve.add_argument("--lease-ms", type=int, default=10_000, help="session lease without heartbeats (ms)")
    serve.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a config variable")
    serve.add_argument("--server", help="serve only this server of the configuration's servers: section (its SAs "
                                        "and its persistence); default: every SA as one server")
    serve.set_defaults(fn=_serve, log_level="INFO")


