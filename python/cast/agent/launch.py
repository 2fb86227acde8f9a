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
from cast.config.model import ComponentConfig, SystemConfig
from cast.errors import CastError, InvalidArgumentError, LockedError, NotFoundError
from cast.orchestrator.launchers import LaunchError, launcher_for

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
    found = next((s for s in config.servers if s.name == server), None)
    if found is None:
        known = ", ".join(s.name for s in config.servers)
        raise NotFoundError(f"no server '{server}' in {config.source} (servers: {known})")
    if secret_file is None:
        raise LockedError(f"server '{server}': this agent has no --secret-file, and a server verifies component "
                          "tokens with the system secret: start the agent with --secret-file")
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
    return LaunchPlan(None, argv, env, None, name=SERVER_PREFIX + server)


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


def plan_launch(
    config: SystemConfig, component_id: str, contract: Mapping[str, str], agent_env: Mapping[str, str] | None = None
) -> LaunchPlan:
    """The process to start for ``component_id``, or the CastError that says why none can be."""
    check_contract(contract)
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
    full_env = {**env, **launcher.environment(comp, config, env), **contract}
    return LaunchPlan(comp, argv, full_env, launcher.working_directory(comp))


def probe(config: SystemConfig, component_ids: Sequence[str]) -> list[tuple[str, str | None]]:
    """For each component (every launched one if none named): (id, the problem, or None if launchable)."""
    ids = list(component_ids) or [c.id for c in config.components if c.launched]
    results: list[tuple[str, str | None]] = []
    for component_id in ids:
        try:
            comp = find_component(config, component_id)
            if not comp.launched:
                raise LockedError(f"component '{comp.id}' is not launched as a process (in_process or manual)")
            if comp.language == "python":
                problem = missing_module(comp, config)
                if problem is not None:
                    raise LaunchError(problem)
            env = {k: v for k, v in os.environ.items() if k not in PRIVATE_ENV}
            launcher_for(comp.language).command(comp, config, env)
        except CastError as exc:
            results.append((component_id, exc.message))
        else:
            results.append((component_id, None))
    return results
