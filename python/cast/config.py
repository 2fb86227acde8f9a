"""System configuration: the YAML file that describes subarchitectures and components.

This is the minimal form the server needs (SA names, task manager policies,
limits, components with their class and flags). The full validation with
file/line positions, variables and includes belongs to the orchestrator.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from cast.core.policies import TaskPolicy, make_policy
from cast.core.records import Limits
from cast.errors import InvalidArgumentError

__all__ = ["ComponentConfig", "ConfigError", "SubarchitectureConfig", "SystemConfig", "load_config", "parse_config"]


class ConfigError(InvalidArgumentError):
    """A configuration problem; the message names the file and key."""


@dataclass
class ComponentConfig:
    """One component of a subarchitecture."""

    id: str
    subarchitecture: str
    language: str = "python"
    kind: str = "unmanaged"
    cls: str = ""  # python: module:Class; java: class name
    run: str = ""  # cpp: executable
    args: dict[str, Any] = field(default_factory=dict)
    privileged: bool = False
    in_process: bool = False
    restart: str = "on-failure"


@dataclass
class SubarchitectureConfig:
    """One subarchitecture: its task manager policy and its components."""

    name: str
    policy: str = "always"
    policy_options: dict[str, Any] = field(default_factory=dict)
    components: dict[str, ComponentConfig] = field(default_factory=dict)

    def make_policy(self) -> TaskPolicy:
        """The task manager policy object."""
        return make_policy(self.policy, self.policy_options)


@dataclass
class SystemConfig:
    """A whole system."""

    name: str
    subarchitectures: dict[str, SubarchitectureConfig]
    limits: Limits = field(default_factory=Limits)
    source: str = "<config>"

    @property
    def components(self) -> list[ComponentConfig]:
        """Every component, in file order."""
        return [c for sa in self.subarchitectures.values() for c in sa.components.values()]


_TOP_KEYS = {"system", "subarchitectures", "limits"}
_SA_KEYS = {"task_manager", "components"}
_TM_KEYS = {"policy"}
_COMPONENT_KEYS = {"language", "kind", "class", "run", "args", "privileged", "in_process", "restart"}
_LIMIT_KEYS = {f.name for f in fields(Limits)}


def _check_keys(where: str, mapping: dict[str, Any], allowed: set[str], source: str) -> None:
    for key in mapping:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), sorted(allowed), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else f" (allowed: {', '.join(sorted(allowed))})"
            raise ConfigError(f"{source}: unknown key '{where}{key}'{hint}")


def _mapping(value: Any, where: str, source: str) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"{source}: '{where}' must be a mapping, got {type(value).__name__}")
    return value


def parse_config(data: Any, source: str = "<config>") -> SystemConfig:
    """Build a SystemConfig from parsed YAML; ConfigError naming the key on any problem."""
    top = _mapping(data, "(top level)", source)
    _check_keys("", top, _TOP_KEYS, source)
    name = str(top.get("system") or "cast")
    sas_raw = _mapping(top.get("subarchitectures"), "subarchitectures", source)
    if not sas_raw:
        raise ConfigError(f"{source}: 'subarchitectures' must name at least one subarchitecture")
    sas: dict[str, SubarchitectureConfig] = {}
    seen_components: dict[str, str] = {}
    for sa_name, sa_raw in sas_raw.items():
        sa_map = _mapping(sa_raw, f"subarchitectures.{sa_name}", source)
        _check_keys(f"subarchitectures.{sa_name}.", sa_map, _SA_KEYS, source)
        tm = _mapping(sa_map.get("task_manager"), f"subarchitectures.{sa_name}.task_manager", source)
        policy = str(tm.get("policy", "always"))
        options = {k: v for k, v in tm.items() if k != "policy"}
        sa = SubarchitectureConfig(str(sa_name), policy, options)
        try:
            sa.make_policy()
        except InvalidArgumentError as exc:
            raise ConfigError(f"{source}: subarchitectures.{sa_name}.task_manager: {exc.message}") from None
        comps = _mapping(sa_map.get("components"), f"subarchitectures.{sa_name}.components", source)
        for comp_id, comp_raw in comps.items():
            where = f"subarchitectures.{sa_name}.components.{comp_id}"
            c = _mapping(comp_raw, where, source)
            _check_keys(f"{where}.", c, _COMPONENT_KEYS, source)
            if comp_id in seen_components:
                raise ConfigError(
                    f"{source}: component id '{comp_id}' is used twice (in '{seen_components[comp_id]}' and "
                    f"'{sa_name}'): component ids are unique in a system"
                )
            seen_components[str(comp_id)] = str(sa_name)
            sa.components[str(comp_id)] = ComponentConfig(
                id=str(comp_id),
                subarchitecture=str(sa_name),
                language=str(c.get("language", "python")),
                kind=str(c.get("kind", "unmanaged")),
                cls=str(c.get("class", "")),
                run=str(c.get("run", "")),
                args=_mapping(c.get("args"), f"{where}.args", source),
                privileged=bool(c.get("privileged", False)),
                in_process=bool(c.get("in_process", False)),
                restart=str(c.get("restart", "on-failure")),
            )
        sas[str(sa_name)] = sa
    limits_raw = _mapping(top.get("limits"), "limits", source)
    _check_keys("limits.", limits_raw, _LIMIT_KEYS, source)
    for key, value in limits_raw.items():
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise ConfigError(f"{source}: limits.{key} must be a positive whole number, got {value!r}")
    return SystemConfig(name, sas, Limits(**limits_raw), source)


def load_config(path: str | Path) -> SystemConfig:
    """Read and parse a configuration file."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read configuration '{p}': {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: invalid YAML: {exc}") from None
    return parse_config(data, str(p))
