"""The ``cast`` command line: ``cast serve``, ``cast token``."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import shlex
import sys

from cast.auth import TokenSigner, load_or_create_secret, load_secret
from cast.config import load_config
from cast.core.records import Identity
from cast.errors import CastError

__all__ = ["main"]


def _serve(args: argparse.Namespace) -> int:
    from cast.server.app import RunningServer, serve_forever, system_from_config
    from cast.server.in_process import InProcessComponents

    config = load_config(args.config)
    system = system_from_config(config, lease_ms=args.lease_ms)
    signer = TokenSigner(load_or_create_secret(args.secret_file))
    in_process = InProcessComponents(system)

    def started(running: RunningServer) -> None:
        for comp in config.components:
            if comp.in_process:
                in_process.start(comp)
        running.on_stop(in_process.stop_all)

    asyncio.run(serve_forever(system, signer, args.listen, started))
    return 0


def _token(args: argparse.Namespace) -> int:
    secret = load_secret(args.secret_file)
    if secret is None:
        print(
            "cast token: no secret: set CAST_SECRET, pass --secret-file, or run from the directory where "
            "`cast serve` created .cast/secret",
            file=sys.stderr,
        )
        return 2
    sa, privileged, comp_args = args.subarchitecture, args.privileged, {}
    if args.config:
        config = load_config(args.config)
        found = next((c for c in config.components if c.id == args.component), None)
        if found is None:
            known = ", ".join(c.id for c in config.components) or "none"
            print(f"cast token: no component '{args.component}' in {args.config} (known: {known})", file=sys.stderr)
            return 2
        sa, privileged, comp_args = found.subarchitecture, found.privileged or privileged, found.args
    if not sa:
        print("cast token: give --subarchitecture (or --config with the component in it)", file=sys.stderr)
        return 2
    token = TokenSigner(secret).issue(Identity(args.component, sa, privileged), args.ttl)
    env = {
        "CAST_ENDPOINT": args.endpoint,
        "CAST_COMPONENT_ID": args.component,
        "CAST_SUBARCHITECTURE": sa,
        "CAST_TOKEN": token,
        "CAST_ARGS": json.dumps(comp_args),
    }
    if args.json:
        print(json.dumps(env))
    else:
        for key, value in env.items():
            print(f"export {key}={shlex.quote(value)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``cast``."""
    parser = argparse.ArgumentParser(prog="cast", description="CAST on gRPC: working memories for robot components")
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="serve the working memories of a configuration")
    serve.add_argument("config", help="system configuration (YAML)")
    serve.add_argument("--listen", default="127.0.0.1:50051", help="HOST:PORT to listen on; port 0 picks a free one")
    serve.add_argument("--secret-file", help="token secret (default: $CAST_SECRET, else .cast/secret, created)")
    serve.add_argument("--lease-ms", type=int, default=10_000, help="session lease without heartbeats (ms)")
    serve.set_defaults(fn=_serve)

    token = sub.add_parser("token", help="print the launch environment of a component started by hand")
    token.add_argument("component", help="component id")
    token.add_argument("--config", help="take SA, privileged and args from this configuration")
    token.add_argument("--subarchitecture", "--sa", default="", help="the component's SA")
    token.add_argument("--privileged", action="store_true", help="may write every SA")
    token.add_argument("--endpoint", default="127.0.0.1:50051", help="directory endpoint HOST:PORT")
    token.add_argument("--ttl", type=float, default=0, help="seconds until the token expires (0: never)")
    token.add_argument("--secret-file", help="token secret (default: $CAST_SECRET, else .cast/secret)")
    token.add_argument("--json", action="store_true", help="print a JSON object instead of shell exports")
    token.set_defaults(fn=_token)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``cast`` command."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    try:
        return int(args.fn(args))
    except CastError as exc:
        print(f"cast {args.command}: {exc.message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except OSError as exc:
        print(f"cast {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
