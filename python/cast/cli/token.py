"""``cast token COMPONENT``: the launch environment of a component started by hand (dynamic join).

The component's SA, privilege and arguments come from ``--config`` (the
component must be in it), else from ``--sa``/``--privileged``, else from the
running system's directory (a configured component not started yet). The
secret and address are those of the running ``cast run`` (its runtime
directory) unless given.

``--write FILE`` writes the token alone into ``FILE`` (a ``CAST_TOKEN_FILE``),
and with ``--renew`` keeps writing a fresh one every ttl / 3 until stopped, as
``cast run`` renews its components' token files: what the init container and
the sidecar of an exported Kubernetes pod run (docs/deploy.md).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import threading
from pathlib import Path
from typing import Any

from cast.auth import TokenSigner, write_token_file
from cast.cli.connect import SystemClient, add_tls_options, find_endpoint, find_secret, find_tls
from cast.cli.options import parse_sets
from cast.config import load_config
from cast.core.records import Identity
from cast.errors import InvalidArgumentError, NotFoundError
from cast.runtime_dir import RuntimeDir, default_runtime_dir

__all__ = ["add_commands"]


def _token(args: argparse.Namespace) -> int:
    env = os.environ
    if args.renew and not (args.write and args.ttl > 0):
        raise InvalidArgumentError("--renew keeps the file of --write FILE fresh: give --write FILE and --ttl SECONDS "
                                   "(a token with no ttl never needs renewing)")
    runtime = RuntimeDir(Path(args.runtime_dir) if args.runtime_dir else default_runtime_dir(env))
    secret = find_secret(args.secret_file, runtime, env)
    endpoint = find_endpoint(args.endpoint, runtime, env)
    signer = TokenSigner(secret)
    tls = find_tls(args, runtime, env)
    sa, privileged, comp_args, extra = args.subarchitecture, args.privileged, {}, {}
    if args.config:
        config = load_config(args.config, parse_sets(args.set))
        found = config.component(args.component)
        if found is None:
            known = ", ".join(c.id for c in config.components) or "none"
            raise NotFoundError(f"no component '{args.component}' in {args.config} (known: {known})")
        sa, privileged, comp_args = found.subarchitecture, found.privileged or privileged, found.args
        if found.language == "python" and config.python_path:
            parts = [str(p) for p in config.python_path] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
            extra["PYTHONPATH"] = os.pathsep.join(parts)
    elif not sa:
        # Ask the running system about a component it expects.
        tool = signer.issue(Identity("cast-cli", "", False), 60)
        with SystemClient(endpoint, tool, tls=tls) as client:
            info = next((c for c in client.system.components if c.id == args.component), None)
        if info is None:
            raise InvalidArgumentError(
                f"component '{args.component}' is not known to the running system: give --sa SA "
                "(and --privileged if it writes other SAs), or --config CONFIG"
            )
        sa, privileged = info.subarchitecture, info.privileged or privileged
    identity = Identity(args.component, sa, privileged)
    if args.write:
        return _write(signer, identity, args)
    token = signer.issue(identity, args.ttl)
    values = {
        "CAST_ENDPOINT": endpoint,
        "CAST_COMPONENT_ID": args.component,
        "CAST_SUBARCHITECTURE": sa,
        "CAST_TOKEN": token,
        "CAST_ARGS": json.dumps(comp_args),
        **extra,
        # The component needs the same trust as the tool had, or it cannot reach the servers.
        **(tls.env() if tls is not None else {}),
    }
    if args.json:
        print(json.dumps(values))
    else:
        for key, value in values.items():
            print(f"export {key}={shlex.quote(value)}")
    return 0


def _write(signer: TokenSigner, identity: Identity, args: argparse.Namespace) -> int:
    """``--write FILE``: the token into FILE; with ``--renew`` a fresh one every ttl / 3 until SIGTERM or SIGINT."""
    path = Path(args.write)
    write_token_file(path, signer.issue(identity, args.ttl))
    expires = f"expires in {args.ttl:g} s" if args.ttl else "never expires"
    print(f"token of component '{identity.component_id}' written to {path} ({expires})", flush=True)
    if not args.renew:
        return 0
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(max(0.2, args.ttl / 3)):
        write_token_file(path, signer.issue(identity, args.ttl))
    return 0


def add_commands(sub: Any) -> None:
    """Add ``cast token``."""
    token = sub.add_parser("token", help="print the launch environment of a component started by hand")
    token.add_argument("component", help="component id")
    token.add_argument("--config", help="take SA, privileged and args from this configuration")
    token.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a config variable")
    token.add_argument("--subarchitecture", "--sa", default="", help="the component's SA")
    token.add_argument("--privileged", action="store_true", help="may write every SA")
    token.add_argument("--endpoint", help="directory HOST:PORT (default: $CAST_ENDPOINT, else the running `cast run`)")
    token.add_argument("--runtime-dir", help="runtime directory of the running `cast run` (default: .cast)")
    token.add_argument("--ttl", type=float, default=0, help="seconds until the token expires (0: never)")
    token.add_argument("--secret-file", help="token secret (default: $CAST_SECRET, else the runtime directory's)")
    token.add_argument("--json", action="store_true", help="print a JSON object instead of shell exports")
    token.add_argument("--write", metavar="FILE", help="write the token alone to FILE (mode 0600, replaced "
                                                       "atomically), for a component given CAST_TOKEN_FILE=FILE")
    token.add_argument("--renew", action="store_true", help="with --write and --ttl: keep running, writing a fresh "
                                                            "token every ttl / 3 seconds until stopped")
    add_tls_options(token)
    token.set_defaults(fn=_token)
