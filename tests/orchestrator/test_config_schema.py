"""The configuration's JSON Schema: shipped files pass it as they are, it says what the loader accepts, and
cast check reports its violations on their lines."""

from __future__ import annotations

import ast
import json
import os
import textwrap
from dataclasses import MISSING, fields, is_dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from jsonschema import Draft7Validator

from cast.config import model as m
from cast.config import read_config, ros
from cast.config.schema import mapping_properties, resolve, system_schema
from cast.config.schema_gen import generated, main
from cast.core.records import Limits, Quota
from tests.conftest import ROOT
from tests.orchestrator.test_config import one, problems

SCHEMA_PATH = ROOT / "python" / "cast" / "config" / "system.schema.json"
MODELINE = "# yaml-language-server: $schema="
SHIPPED = sorted([*ROOT.glob("configs/*.yaml"), *ROOT.glob("configs/*/*.yaml"),
                  *(p for p in ROOT.glob("examples/**/system.yaml") if "node_modules" not in p.parts)])


def schema() -> dict[str, Any]:
    return json.loads(SCHEMA_PATH.read_text())


def props(*path: str) -> dict[str, Any]:
    """The properties of a mapping of the schema: ``("limits",)`` at the top, ``("#restart",)`` a definition."""
    s = schema()
    node: dict[str, Any] = s
    for step in path:
        node = s["definitions"][step[1:]] if step.startswith("#") else mapping_properties(node, s)[step]
    return mapping_properties(node, s)


def default(node: dict[str, Any]) -> Any:
    node = dict(resolve(node, schema()))
    if "default" not in node and node.get("allOf"):
        return default(node["allOf"][0])
    return node.get("default", MISSING)


def field_defaults(cls: type) -> dict[str, Any]:
    out = {}
    for f in fields(cls):
        if f.default is not MISSING:
            out[f.name] = f.default
        elif f.default_factory is not MISSING:
            out[f.name] = f.default_factory()
    return out


# ------------------------------------------------------------------ shipped files and editors

def test_the_shipped_configurations_are_found() -> None:
    names = {str(p.relative_to(ROOT)) for p in SHIPPED}
    assert {"configs/demo.yaml", "configs/demo/segmenter-cpp.yaml", "configs/pipeline/one-sa.yaml",
            "examples/node/system.yaml", "examples/cpp/hello/system.yaml"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_shipped_configuration_names_the_schema_on_its_first_line(path: Path) -> None:
    first = path.read_text().splitlines()[0]
    assert first.startswith(MODELINE), f"{path}: the first line must be '{MODELINE}<relative path>'"
    assert (path.parent / first.removeprefix(MODELINE)).resolve() == SCHEMA_PATH


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_shipped_configuration_is_valid_under_the_schema_with_jsonschema_itself(path: Path) -> None:
    errors = list(Draft7Validator(schema()).iter_errors(yaml.safe_load(path.read_text())))
    assert not errors, [f"{list(e.absolute_path)}: {e.message}" for e in errors]


def test_the_schema_is_a_draft_07_schema_and_refuses_what_cast_check_refuses() -> None:
    Draft7Validator.check_schema(schema())
    validator = Draft7Validator(schema())

    def valid(data: dict[str, Any]) -> bool:
        return validator.is_valid(data)

    assert valid({"subarchitectures": {"v": {"components": {"c": {"class": "a:B"}}}}})
    assert not valid({"subarchitectures": {"v": {"components": {"c": {"clas": "a:B"}}}}})
    assert not valid({"limits": {"max_entries": 0}})
    assert not valid({"servers": {"a": {"listen": "nowhere", "subarchitectures": ["v"]}}})
    # The task managers' part, generated from the policy classes, knows each built-in policy's options.
    assert valid({"subarchitectures": {"v": {"task_manager": {"policy": "fifo", "max_waiting": 2}}}})
    assert not valid({"subarchitectures": {"v": {"task_manager": {"policy": "fifo", "max_concurent": 2}}}})
    assert not valid({"subarchitectures": {"v": {"task_manager": {"max_concurrent": 2}}}})  # always takes none
    assert not valid({"subarchitectures": {"v": {"task_manager": {"policy": "fido"}}}})
    assert valid({"subarchitectures": {"v": {"task_manager": {"policy": "my.pkg:Mine", "anything": 1}}}})


def test_the_generated_part_is_up_to_date() -> None:
    assert generated(schema()) == schema(), "run: python -m cast.config.schema_gen --write"
    assert system_schema() == schema()  # the package reads this very file
    assert main(["--check"]) == 0


def test_the_check_of_the_generated_part_can_fail(monkeypatch: pytest.MonkeyPatch) -> None:
    import cast.config.schema_gen as module
    from cast.core.policies import AlwaysPolicy

    class Newer(AlwaysPolicy):
        """A policy the file does not know yet."""

        name = "newer"

    monkeypatch.setattr(module, "BUILTIN_POLICIES", {**module.BUILTIN_POLICIES, "newer": Newer})
    assert generated(schema()) != schema()
    assert main(["--check"]) == 1


# ----------------------------------------------------- one description: schema, loader, model

def test_limit_and_quota_keys_and_defaults_are_the_dataclasses() -> None:
    for section, cls in ((("limits",), Limits), (("#component", "quota"), Quota)):
        keys = props(*section)
        assert set(keys) == {f.name for f in fields(cls)}, section
        assert {k: default(v) for k, v in keys.items()} == field_defaults(cls), section


def test_every_section_maps_onto_its_model_with_the_same_defaults() -> None:
    # schema key -> model field, for the mappings the builder turns into one dataclass each.
    sections: list[tuple[tuple[str, ...], type, dict[str, str], set[str]]] = [
        (("orchestrator",), m.OrchestratorOptions, {}, set()),
        (("auth",), m.AuthConfig, {}, set()),
        (("tls",), m.TlsConfig, {}, set()),
        (("#persistence",), m.PersistenceConfig, {}, set()),
        (("#restart",), m.RestartPolicy, {"policy": "mode"}, set()),
        (("#server",), m.ServerConfig, {}, {"name"}),
        (("#component",), m.ComponentConfig, {"class": "cls"},
         {"id", "command", "base_dir", "position", "positions"}),
        (("#subarchitecture",), m.SubarchitectureConfig, {"task_manager": "policy"},
         {"name", "policy_options", "position"}),
        ((), m.SystemConfig, {"system": "name", "include": "files", "components": "subarchitectures",
                            "persistence": "servers"}, {"source"}),
        (("#ros_bridge",), ros.RosBridgeConfig, {}, set()),
        (("#ros_to_wm",), ros.RosToWm, {}, set()),
        (("#ros_to_ros",), ros.WmToRos, {}, set()),
        (("#ros_watch",), ros.RosWatch, {}, set()),
        (("#ros_qos",), ros.RosQos, {}, set()),
    ]
    for section, cls, renamed, derived in sections:
        keys = props(*section)
        model = {f.name for f in fields(cls)} - derived
        assert {renamed.get(k, k) for k in keys} == model, (section, cls.__name__)
        defaults = field_defaults(cls)
        for key, node in keys.items():
            model_default = defaults.get(renamed.get(key, key), MISSING)
            if default(node) is not MISSING and model_default is not MISSING and not is_dataclass(model_default):
                assert default(node) == model_default, (section, key)
    assert default(props("#server")["listen"]) == m.DEFAULT_LISTEN
    assert default(props("#component")["restart"]) == m.RestartPolicy().mode


def _other_value(node: dict[str, Any], now: Any) -> Any:
    node = dict(resolve(node, schema()))
    enum = [v for v in node.get("enum", []) if v is not None]
    if enum:
        return next(v for v in enum if v != now)
    kind = node["type"]
    return {"boolean": not now, "integer": now + 3, "number": now + 1.5}[kind]


@pytest.mark.parametrize(("section", "attribute"), [
    (("orchestrator",), "orchestrator"), (("auth",), "auth"), (("limits",), "limits"),
])
def test_every_key_of_a_settings_section_reaches_the_model(tmp_path: Path, section: tuple[str, ...],
                                                           attribute: str) -> None:
    keys = props(*section)
    values = {k: _other_value(v, default(v)) for k, v in keys.items()}
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump({"subarchitectures": {"v": {}}, section[0]: values}))
    config, found = read_config(path, environ={})
    assert config is not None and not found.items, [str(p) for p in found.items]
    model = getattr(config, attribute)
    assert {k: getattr(model, k) for k in values} == values


def test_every_key_of_a_component_reaches_the_model(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent("""\
        subarchitectures:
          v:
            components:
              c:
                language: java
                kind: managed
                class: a.B
                run: ignored
                args: {n: 1}
                privileged: true
                manual: true
                restart: {policy: always, max_restarts: 7, backoff: 2, max_backoff: 9}
                classpath: [x.jar]
                quota: {entries: 3, bytes: 4}
                host: arm
          w:
            components:
              p: {class: "m:C", in_process: true, restart: never}
              r:
                language: ros
                ros:
                  version: 1
                  python: /usr/bin/python3
                  node: bridge
                  namespace: /robot
                  status_period: 2.5
                  to_wm:
                    - {topic: /scan, type: sensor_msgs/LaserScan, subarchitecture: w, store: each, id: laser, keep: 7,
                       max_rate: 5, buffer: 9, qos: {reliability: best_effort, durability: transient_local,
                       history: keep_all, depth: 3}}
                  to_ros:
                    - {watch: {subarchitecture: v, type: ros1.geometry_msgs.msg.Twist, author: planner},
                       topic: cmd_vel, type: geometry_msgs/Twist}
        hosts: {arm: "10.0.0.2:7070"}
        """))
    config, found = read_config(path, environ={})
    assert config is not None and not found.items, [str(p) for p in found.items]
    c, p, r = config.components
    assert set(props("#component")) - {"subarchitecture"} == {
        "language", "kind", "class", "run", "args", "privileged", "manual", "restart", "classpath", "quota",
        "in_process", "host", "ros"}  # each is set below, so a new key makes this test say so
    assert r.ros == ros.RosBridgeConfig(
        version=1, python="/usr/bin/python3", node="bridge", namespace="/robot", status_period=2.5,
        to_wm=(ros.RosToWm("/scan", "sensor_msgs/LaserScan", "w", "each", "laser", 7, 5.0, 9,
                           ros.RosQos("best_effort", "transient_local", "keep_all", 3)),),
        to_ros=(ros.WmToRos(ros.RosWatch("v", "ros1.geometry_msgs.msg.Twist", "", "planner"), "cmd_vel",
                            "geometry_msgs/Twist"),))
    assert ros.RosBridgeConfig.from_dict(r.ros.to_dict()) == r.ros
    assert set(props("#ros_bridge")) == {f.name for f in fields(ros.RosBridgeConfig)}
    assert (c.language, c.kind, c.cls, c.run, c.args, c.privileged, c.manual) == (
        "java", "managed", "a.B", "ignored", {"n": 1}, True, True)
    assert c.restart == m.RestartPolicy("always", 7, 2.0, 9.0)
    assert c.classpath == [str(tmp_path / "x.jar")] and c.quota == Quota(3, 4)
    assert p.in_process and p.restart == m.RestartPolicy("never")
    assert (c.host, p.host, config.hosts["arm"].agent) == ("arm", "local", "10.0.0.2:7070")


def _nodes(node: Any, where: str = "") -> list[tuple[str, dict[str, Any]]]:
    if isinstance(node, list):
        return [n for i, item in enumerate(node) for n in _nodes(item, f"{where}[{i}]")]
    if not isinstance(node, dict):
        return []
    found = [(where, node)]
    for key, value in node.items():
        found += _nodes(value, f"{where}/{key}")
    return found


def test_the_schema_keeps_to_what_the_translation_of_its_errors_assumes() -> None:
    s = schema()
    for where, node in _nodes(s):
        if "properties" in node and "allOf" not in node and "/if" not in where:
            # A mapping with named keys refuses others (reported as unknown keys, with a suggestion); a mapping
            # composed with allOf gets its keys from its parts.
            assert node.get("additionalProperties") is False, where
        for branch in node.get("anyOf", []):
            assert "type" in resolve(branch, s), f"{where}: every anyOf branch names its type (errors pick by type)"
        if "propertyNames" in node:
            assert "title" in node["propertyNames"] and "errorMessage" in node["propertyNames"], where
    names = {json.dumps(n["propertyNames"]["pattern"]) for w, n in _nodes(s) if "propertyNames" in n
             and w != "/properties/variables"}
    assert len(names) == 1  # SA names and component ids follow one rule


def test_variable_names_in_the_schema_are_the_loaders() -> None:
    from cast.config import source

    loader = source._NAME.pattern.removesuffix(r"\Z")
    assert schema()["properties"]["variables"]["propertyNames"]["pattern"] == f"^{loader}$"


# ----------------------------------------------------------- cast check on top of the schema

def test_schema_violations_are_reported_on_their_lines_once_each(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        python_path: [5, ok]
        subarchitectures:
          vision:
            components:
              a: {language: other, run: {a: b}}
              b: {class: a:B, restart: 5}
              c: {class: a:B, subarchitecture: vision}
              d: {class: a:B, privileged: {a: 1}}
              e: {class: {x: 1}}
          "bad name": {}
        servers:
          one: {listen: "host:99999", subarchitectures: [vision]}
          two:
            listen: 5
        limits: {max_entrys: 3, max_entries: 2.0}
        tls: {ca: a, key: b, client_key: c}
        orchestrator: {stop_timeout: -1}
        """)
    one(found, 1, "python_path", "must be a path or a list of paths, not int 5")
    one(found, 5, "a.run", "must be a command line (text or a list of words), not a mapping")
    one(found, 6, "b.restart", "must be never, on-failure, always, or a mapping {policy:, max_restarts:, "
                               "backoff:}, not int 5")
    one(found, 7, "c.subarchitecture", "only a component in the top-level components: mapping names its SA")
    one(found, 8, "d.privileged", "must be true or false, not a mapping")
    one(found, 9, "e.class", "must be a word or text, not a mapping")
    one(found, 10, "subarchitectures.bad name", "subarchitecture name 'bad name' must be 1 to 128 letters")
    one(found, 12, "servers.one.listen", "'host:99999' must be HOST:PORT (port 0 picks a free port)")
    one(found, 13, "servers.two.subarchitectures", "list the SAs this server hosts")
    one(found, 14, "servers.two.listen", "must be HOST:PORT (port 0 picks a free port), not int 5")
    one(found, 15, "limits.max_entrys", "unknown key 'max_entrys' (did you mean 'max_entries'?)")
    one(found, 15, "limits.max_entries", "must be a positive whole number, not 2.0")
    one(found, 16, "tls.cert", "needs a file path")
    one(found, 16, "tls.client_cert", "give client_cert and client_key together, or neither")
    one(found, 17, "orchestrator.stop_timeout", "must be a number >= 0, not -1")
    assert len(found) == 15, "\n".join(map(str, found))  # one line per mistake: a wrong class is not also missing


def test_a_wrong_value_is_reported_and_its_default_used(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text("subarchitectures: {v: {components: {c: {class: 'a:B', restart: {max_restarts: -1}}}}}\n"
                    "orchestrator: {stop_timeout: -1, lease_ms: 5}\n")
    config, found = read_config(path, environ={})
    assert config is not None and len(found.errors) == 2
    assert config.orchestrator == m.OrchestratorOptions(lease_ms=5)
    assert config.components[0].restart == m.RestartPolicy()


# ------------------------------------------------------------------ the config imports no layer above it

FORBIDDEN = ("cast.orchestrator", "cast.server", "cast.cli", "cast.client", "cast.v1", "grpc", "grpc_health",
             "grpc_reflection")
PYTHON = ROOT / "python"


def _imports(path: Path) -> list[tuple[int, str]]:
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):  # function-level imports too
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
    return found


def _module_file(name: str) -> Path | None:
    base = PYTHON.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.exists():
            return candidate
    return None


def forbidden_imports(start: list[Path]) -> list[str]:
    """Each forbidden import in ``start`` and in the cast modules they import, one after another."""
    seen: set[Path] = set()
    todo = list(start)
    offending: list[str] = []
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        for line, name in _imports(path):
            if any(name == bad or name.startswith(bad + ".") for bad in FORBIDDEN):
                offending.append(f"{os.path.relpath(path, ROOT)}:{line}: imports {name}")
            elif name.startswith("cast."):
                parts = name.split(".")
                # The module and its packages (cast.core.policies runs cast/core/__init__.py), not the top
                # package `cast`, whose __init__ is the public API of the client library.
                for end in range(2, len(parts) + 1):
                    found = _module_file(".".join(parts[:end]))
                    if found is not None:
                        todo.append(found)
    return offending


def test_the_configuration_imports_nothing_above_it() -> None:
    config_modules = sorted((PYTHON / "cast" / "config").glob("*.py"))
    assert len(config_modules) >= 8
    offending = forbidden_imports(config_modules)
    assert not offending, "\n".join(offending)


def test_the_import_check_sees_imports_through_other_modules(tmp_path: Path) -> None:
    # The scan must see what it looks for, or the test above could never fail.
    assert any("cast.orchestrator" in o for o in forbidden_imports([PYTHON / "cast" / "cli" / "run.py"]))
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from cast.orchestrator.preflight import preflight\n")
    assert forbidden_imports([module]) == [f"{os.path.relpath(module, ROOT)}:2: imports cast.orchestrator.preflight"]
