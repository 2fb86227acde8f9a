"""``cast agent --listen ADDR --root DIR``: the per-host daemon of multi-host systems (docs/multihost.md)."""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path
from typing import Any

__all__ = ["add_commands"]


def _agent(args: argparse.Namespace) -> int:
    from cast.agent.app import serve_agent
    from cast.agent.trust import AgentTrust

    trust = AgentTrust.from_files(args.secret_file, args.tls_cert, args.tls_key, args.tls_ca)
    log_dir = Path(args.log_dir) if args.log_dir else None
    asyncio.run(serve_agent(args.listen, Path(args.root), trust, log_dir))
    return 0


def add_commands(sub: Any) -> None:
    """Add ``cast agent``."""
    agent = sub.add_parser("agent", help="run components on this host for an orchestrator on another one")
    agent.add_argument("--listen", required=True, help="HOST:PORT to listen on (that address only; port 0 picks "
                                                       "a free one)")
    agent.add_argument("--root", required=True, help="the checkout or install holding the configurations and "
                                                     "components, the same as the orchestrator's")
    agent.add_argument("--secret-file", help="the system secret: every call must carry a privileged token for "
                                             "'orchestrator' signed with it")
    agent.add_argument("--tls-cert", help="the agent's certificate (PEM)")
    agent.add_argument("--tls-key", help="the agent's private key (PEM)")
    agent.add_argument("--tls-ca", help="mutual TLS: callers need a client certificate signed by this CA")
    agent.add_argument("--log-dir", help="where the agent also keeps each process's output "
                                         "(default: ROOT/.cast/agent/logs/SYSTEM/COMPONENT.log)")
    agent.set_defaults(fn=_agent, log_level="INFO")
