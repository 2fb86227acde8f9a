"""The JSON Schema of the system configuration (``system.schema.json``, shipped with the package).

The schema is the one description of the configuration's keys, types, enums,
defaults and descriptions: ``cast check`` validates against it
(:mod:`cast.config.schema_check` says where each problem is written), the
builder takes its defaults from it, and editors read it through the
``# yaml-language-server: $schema=...`` line of a configuration.

One part is generated: ``definitions.task_manager`` comes from the task policy
classes' declared options (:mod:`cast.config.schema_gen`), so a policy's options
are written once, in its class.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from functools import cache
from importlib import resources
from typing import Any

__all__ = [
    "PY_CLASS_PATTERN",
    "SCHEMA_FILE",
    "TEXT",
    "defaults",
    "mapping_properties",
    "resolve",
    "runtime_schema",
    "system_schema",
]

SCHEMA_FILE = "system.schema.json"
# A scalar read as text: YAML's `system: 2024` is the name "2024", and an empty value means the default.
TEXT = ["string", "number", "null"]
PY_CLASS_PATTERN = r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$"  # module:Class, for component and policy classes


@cache
def _schema_text() -> str:
    return resources.files("cast.config").joinpath(SCHEMA_FILE).read_text(encoding="utf-8")


def system_schema() -> dict[str, Any]:
    """The schema as shipped (a fresh copy: callers may change it)."""
    loaded: dict[str, Any] = json.loads(_schema_text())
    return loaded


@cache
def _runtime_schema() -> dict[str, Any]:
    schema = system_schema()
    generated = schema["definitions"]["task_manager"]
    # The task manager's policy is a built-in name or a user's module:Class, whose options are known only once
    # the class is imported; so cast check asks the policy class itself (validate.py), and the schema pass checks
    # only that task_manager is a mapping and its policy a word. The generated part is the same declarations,
    # exported for editors.
    schema["definitions"]["task_manager"] = {
        "type": generated["type"],
        "properties": {"policy": {"type": TEXT}},
    }
    return schema


def runtime_schema() -> dict[str, Any]:
    """The schema ``cast check`` validates a tree against: the shipped one less the task managers' options."""
    return _runtime_schema()


def resolve(node: Mapping[str, Any], schema: Mapping[str, Any]) -> Mapping[str, Any]:
    """``node`` with its ``$ref`` followed (``#/definitions/NAME`` references only)."""
    while "$ref" in node:
        ref = str(node["$ref"])
        prefix = "#/definitions/"
        if not ref.startswith(prefix):
            raise ValueError(f"only {prefix}NAME references are used in the configuration schema, not {ref}")
        node = schema["definitions"][ref.removeprefix(prefix)]
    return node


def mapping_properties(node: Mapping[str, Any], schema: Mapping[str, Any]) -> dict[str, Any]:
    """The properties of the mapping ``node`` describes, through ``$ref``, ``allOf`` and an ``anyOf``'s mapping."""
    node = resolve(node, schema)
    found: dict[str, Any] = {}
    for part in node.get("allOf", []):
        found.update(mapping_properties(part, schema))
    for branch in node.get("anyOf", []):
        branch = resolve(branch, schema)
        if branch.get("type") == "object":
            found.update(mapping_properties(branch, schema))
    found.update(node.get("properties", {}))
    return found


def defaults(*path: str) -> dict[str, Any]:
    """The default of each key of one mapping of the schema that has one.

    ``path`` names the mapping: ``()`` the top level, ``("limits",)`` a top-level
    section, ``("#component",)`` a definition, ``("#component", "quota")`` a mapping in it.
    """
    schema = runtime_schema()
    node: Mapping[str, Any] = schema
    for step in path:
        node = schema["definitions"][step[1:]] if step.startswith("#") else mapping_properties(node, schema)[step]
    found = {key: _default(value, schema) for key, value in mapping_properties(node, schema).items()}
    return {key: value for key, value in found.items() if value is not _NO_DEFAULT}


_NO_DEFAULT = object()


def _default(node: Mapping[str, Any], schema: Mapping[str, Any]) -> Any:
    """A node's default, also where it comes through ``$ref`` or ``allOf`` (``restart:`` from its definition)."""
    node = resolve(node, schema)
    if "default" in node:
        return node["default"]
    for part in node.get("allOf", []):
        found = _default(part, schema)
        if found is not _NO_DEFAULT:
            return found
    return _NO_DEFAULT
