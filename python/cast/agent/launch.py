"""What the agent starts: a component's command line, environment and directory, built on this host.

The orchestrator names a configuration file relative to the agent's root and a
component; the agent loads that file with the project's own loader and asks
the same launchers ``cast run`` uses (:mod:`cast.orchestrator.launchers`), so
every path (``python_path``, ``run:``, ``classpath:``, the C++ bin directory)
resolves on this host. Nothing here starts a process: :mod:`cast.agent.processes`
does, once :func:`plan_launch` has said what to start.
"""

from __future__ import annotations

import importlib.machinery
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from cast.config import load_config
from cast.config.model import ComponentConfig, ServerConfig, SystemConfig
from cast.errors import CastError, InvalidArgumentError, LockedError, NotFoundError
from cast.orchestrator.launchers import LaunchError, launcher_for, stack_dump_signal
from cast.orchestrator.security import component_tls
from cast.signals import STACK_DUMP_SIGNAL

__all__ = [
    "PRIVATE_ENV", "SERVER_PREFIX", "LaunchPlan", "check_contract", "load_from_root", "plan_launch", "plan_server",
    "probe",
]

PRIVATE_ENV = ("CAST_SECRET", "CAST_SECRET_FILE")
"""Never passed to a component: with the secret a component could sign any identity."""


@dataclass(frozen=True)
class LaunchPlan:
    """What to start for one component: argv, the full environment, the working directory."""

    component: ComponentConfig | None  # None for a server (plan_server)
    argv: list[str]
    env: dict[str, str]
    cwd: Path | None
    name: str = ""  # the process's name in the table and the events, when not a component's id
    token_file: bool = False  # write CAST_TOKEN to a file of this host, named in CAST_TOKEN_FILE (renewed)
    dump_signal: int | None = None  # sent before the SIGKILL of a stop that timed out (stacks to the log)

    @property
    def process_id(self) -> str:
        """The name the process table, Stop and the events know it by."""
        return self.name or (self.component.id if self.component is not None else "")


SERVER_PREFIX = "server:"
"""A server started by an agent is known as ``server:NAME`` (no component id has a colon)."""


def plan_server(
    config: SystemConfig, config_file: Path, server: str, routes: Mapping[str, str], await_run: str,
    secret_file: Path | None, sets: Mapping[str, str], agent_env: Mapping[str, str] | None = None,
) -> LaunchPlan:
    """``cast serve CONFIG --server NAME`` on the server's listen: address, with the agent's secret file."""
    found = _startable_server(config, server, secret_file)
    argv = [sys.executable, "-m", "cast.cli", "serve", str(config_file), "--server", server,
            "--listen", found.listen, "--secret-file", str(secret_file),
            "--lease-ms", str(config.orchestrator.lease_ms)]
    for name, value in sets.items():
        argv += ["--set", f"{name}={value}"]
    for sa, address in routes.items():
        argv += ["--route", f"{sa}={address}"]
    if await_run:
        argv += ["--await-run", await_run]
    env = {k: v for k, v in (os.environ if agent_env is None else agent_env).items() if k not in PRIVATE_ENV}
    env["PYTHONUNBUFFERED"] = "1"
    return LaunchPlan(None, argv, env, None, name=SERVER_PREFIX + server, dump_signal=STACK_DUMP_SIGNAL)


def load_from_root(root: Path, config_path: str, sets: Mapping[str, str]) -> SystemConfig:
    """The configuration ``config_path`` (relative to ``root``); InvalidArgumentError if outside or wrong."""
    if not config_path:
        raise InvalidArgumentError("no config_path: name the configuration file, relative to the agent's --root")
    relative = Path(config_path)
    if relative.is_absolute():
        raise InvalidArgumentError(
            f"config_path '{config_path}' is absolute: give it relative to the agent's --root ({root}), "
            "which holds the same checkout as the orchestrator's"
        )
    path = (root / relative).resolve()
    if not path.is_relative_to(root.resolve()):
        raise InvalidArgumentError(f"config_path '{config_path}' leaves the agent's --root ({root})")
    if not path.is_file():
        raise NotFoundError(
            f"no configuration '{config_path}' under the agent's --root ({root}): every host needs the same "
            "checkout or install as the orchestrator's (docs/multihost.md)"
        )
    return load_config(path, dict(sets))


def find_component(config: SystemConfig, component_id: str) -> ComponentConfig:
    """The component ``component_id``; NOT_FOUND naming the known ones."""
    for comp in config.components:
        if comp.id == component_id:
            return comp
    known = ", ".join(c.id for c in config.components) or "none"
    raise NotFoundError(f"no component '{component_id}' in {config.source} (components: {known})")


def missing_module(component: ComponentConfig, config: SystemConfig) -> str | None:
    """Why a Python component's module cannot be found here, or None if it can.

    The module is looked up on the configuration's ``python_path`` and then the
    agent's own ``sys.path`` (where the runner's child finds ``cast``), without
    importing it: importing users' code into the agent would run it in the
    daemon. Whether the class exists in the module is the runner's to say (it
    exits 2, reported as an exit).
    """
    module, sep, cls = component.cls.partition(":")
    if not sep or not module or not cls:
        return f"component '{component.id}': class '{component.cls}' must be written module:Class"
    search: Sequence[str] | None = [*(str(p) for p in config.python_path), *sys.path]
    found = None
    for part in module.split("."):
        found = importlib.machinery.PathFinder.find_spec(part, search)
        if found is None:
            break
        search = found.submodule_search_locations
        if search is None:
            search = []
    if found is None:
        where = ", ".join(str(p) for p in config.python_path) or "no python_path"
        return (f"component '{component.id}': module '{module}' is not found on this host (python_path: {where}): "
                "check that the agent's --root holds the same checkout as the orchestrator's")
    return None


def check_contract(env: Mapping[str, str]) -> None:
    """InvalidArgumentError unless every name is a ``CAST_*`` launch-contract variable other than the secret."""
    wrong = sorted(name for name in env if not name.startswith("CAST_") or name in PRIVATE_ENV)
    if wrong:
        raise InvalidArgumentError(
            f"launch environment names {', '.join(wrong)}: only the launch contract (CAST_* variables) is "
            "accepted, and never CAST_SECRET or CAST_SECRET_FILE"
        )


AGENT_ENV = ("CAST_TOKEN_FILE", "CAST_TLS_CA", "CAST_TLS_CERT", "CAST_TLS_KEY", "CAST_TLS_SERVER_NAME")
"""Launch-contract variables the agent sets itself: paths on its own host, not the orchestrator's."""


def plan_launch(
    config: SystemConfig, component_id: str, contract: Mapping[str, str], agent_env: Mapping[str, str] | None = None,
    token_file: bool = False,
) -> LaunchPlan:
    """The process to start for ``component_id``, or the CastError that says why none can be."""
    check_contract(contract)
    contract = {k: v for k, v in contract.items() if k not in AGENT_ENV}
    if token_file and not contract.get("CAST_TOKEN"):
        raise InvalidArgumentError(f"component '{component_id}': token_file needs CAST_TOKEN in the launch "
                                   "environment (the token to write)")
    comp = find_component(config, component_id)
    if not comp.launched:
        raise LockedError(f"component '{comp.id}' is not launched as a process (in_process or manual): "
                          "it has nothing to start on an agent")
    env = {k: v for k, v in (os.environ if agent_env is None else agent_env).items() if k not in PRIVATE_ENV}
    if comp.language == "python":
        problem = missing_module(comp, config)
        if problem is not None:
            raise LaunchError(problem)
    launcher = launcher_for(comp.language)
    argv = launcher.command(comp, config, env)
    full_env = {**env, **launcher.environment(comp, config, env), **contract, **_tls_env(config)}
    return LaunchPlan(comp, argv, full_env, launcher.working_directory(comp), token_file=token_file,
                      dump_signal=stack_dump_signal(launcher))


def _tls_env(config: SystemConfig) -> dict[str, str]:
    """``CAST_TLS_*`` from the configuration's ``tls:`` files on this host; LaunchError naming one missing."""
    client = component_tls(config)
    if client is None:
        return {}
    for path in (client.ca, client.cert, client.key):
        if path is not None and not path.is_file():
            raise LaunchError(f"TLS file {path} (tls: in {config.source}) is not on this host: every host needs "
                              "the system's TLS files where the configuration says (a relative path is under "
                              "the agent's --root; docs/multihost.md)")
    return client.env()


def probe(config: SystemConfig, ids: Sequence[str], secret_file: Path | None = None) -> list[tuple[str, str | None]]:
    """For each id (every launched component if none named): (id, the problem, or None if it could start here).

    An id ``server:NAME`` asks about a server: this agent needs a --secret-file to start one, and the
    server's TLS files must be on this host.
    """
    ids = list(ids) or [c.id for c in config.components if c.launched]
    results: list[tuple[str, str | None]] = []
    for process_id in ids:
        try:
            if process_id.startswith(SERVER_PREFIX):
                _startable_server(config, process_id.removeprefix(SERVER_PREFIX), secret_file)
            else:
                _probe_component(config, process_id)
        except CastError as exc:
            results.append((process_id, exc.message))
        else:
            results.append((process_id, None))
    return results


def _probe_component(config: SystemConfig, component_id: str) -> None:
    comp = find_component(config, component_id)
    if not comp.launched:
        raise LockedError(f"component '{comp.id}' is not launched as a process (in_process or manual)")
    if comp.language == "python":
        problem = missing_module(comp, config)
        if problem is not None:
            raise LaunchError(problem)
    env = {k: v for k, v in os.environ.items() if k not in PRIVATE_ENV}
    launcher_for(comp.language).command(comp, config, env)
    _tls_env(config)


def _startable_server(config: SystemConfig, name: str, secret_file: Path | None) -> ServerConfig:
    """The server ``name``, if this agent can start it: it has the secret, and the TLS files are here."""
    found = next((s for s in config.servers if s.name == name), None)
    if found is None:
        known = ", ".join(s.name for s in config.servers)
        raise NotFoundError(f"no server '{name}' in {config.source} (servers: {known})")
    if secret_file is None:
        raise LockedError(f"server '{name}': this agent has no --secret-file, and a server verifies component "
                          "tokens with the system secret: start the agent with --secret-file")
    tls = config.tls
    for path in ((tls.ca, tls.cert, tls.key) if tls is not None else ()):
        if not path.is_file():
            raise LaunchError(f"server '{name}': TLS file {path} (tls: in {config.source}) is not on this host "
                              "(a relative path is under the agent's --root; docs/multihost.md)")
    return found
