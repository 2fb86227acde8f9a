"""The generated part of the configuration's JSON Schema, and the command that writes it.

``definitions.task_manager`` of ``system.schema.json`` comes from the built-in
task policies and the options each declares (:class:`cast.core.policies.PolicyOption`),
so a policy's options are written once, in its class. After changing a built-in
policy::

    python -m cast.config.schema_gen --write

``--check`` exits 1 if the file is out of date (a test does the same). The rest
of the file is written by hand; ``--write`` keeps it and lays the whole file out
the same way.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from cast.config.schema import PY_CLASS_PATTERN, SCHEMA_FILE
from cast.core.policies import BUILTIN_POLICIES, DEFAULT_POLICY

__all__ = ["generated", "main", "render", "task_manager_definition"]


def task_manager_definition() -> dict[str, Any]:
    """``definitions.task_manager``, generated from the built-in policies and their declared options."""
    names = list(BUILTIN_POLICIES)
    rules: list[dict[str, Any]] = []
    for name, cls in BUILTIN_POLICIES.items():
        condition: dict[str, Any] = {"properties": {"policy": {"const": name}}}
        if name != DEFAULT_POLICY:  # no policy: key means the default one
            condition["required"] = ["policy"]
        options = {o.name: o.json_schema() for o in cls.options or ()}
        rules.append({"if": condition, "then": {"properties": {"policy": True, **options},
                                                 "additionalProperties": False}})
    return {
        "description": "The SA's task manager: which proposed tasks run. policy: names a built-in policy or your "
                       "own class; the other keys are the policy's options.",
        "type": ["object", "null"],
        "properties": {
            "policy": {
                "description": "A built-in policy, or your own as module:Class (a subclass of cast.TaskPolicy on "
                               "python_path; its declared options are checked too).",
                "default": DEFAULT_POLICY,
                "anyOf": [
                    {"type": "string", "enum": names,
                     # enumDescriptions: what VS Code's and yaml-language-server's completion shows for each name.
                     "enumDescriptions": [_first_line(BUILTIN_POLICIES[n].__doc__) for n in names]},
                    {"type": "string", "pattern": PY_CLASS_PATTERN},
                ],
                "errorMessage": f"must be one of {', '.join(names)}, or your own class as module:Class",
            },
        },
        "allOf": rules,
    }


def _first_line(doc: str | None) -> str:
    return doc.strip().splitlines()[0].replace("``", "") if doc else ""


def generated(schema: Mapping[str, Any]) -> dict[str, Any]:
    """``schema`` with its generated part as the code says it is now."""
    out = copy.deepcopy(dict(schema))
    out["definitions"]["task_manager"] = task_manager_definition()
    return out


def render(value: Any, indent: int = 0, lead: int = 0, width: int = 118) -> str:
    """JSON text of ``value``: two-space indents, a mapping or list on one line when it fits in ``width``.

    ``lead`` is how many characters stand before the value on its first line (its key).
    """
    flat = json.dumps(value, ensure_ascii=False)
    if not isinstance(value, (dict, list)) or not value or indent + lead + len(flat) <= width:
        return flat
    pad = " " * (indent + 2)
    if isinstance(value, dict):
        items = []
        for key, item in value.items():
            name = json.dumps(key, ensure_ascii=False) + ": "
            items.append(pad + name + render(item, indent + 2, len(name), width))
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    return "[\n" + ",\n".join(pad + render(v, indent + 2, 0, width) for v in value) + "\n" + " " * indent + "]"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cast.config.schema [--write | --check]``: regenerate or check the schema's generated part."""
    parser = argparse.ArgumentParser(prog="python -m cast.config.schema_gen", description=main.__doc__)
    parser.add_argument("--write", action="store_true", help="rewrite the schema file with the generated part")
    parser.add_argument("--check", action="store_true", help="exit 1 if the schema file is out of date")
    args = parser.parse_args(argv)
    path = Path(__file__).with_name(SCHEMA_FILE)
    current = json.loads(path.read_text(encoding="utf-8"))
    fresh = generated(current)
    if args.write:
        path.write_text(render(fresh) + "\n", encoding="utf-8")
        print(f"wrote {path}")
        return 0
    if fresh != current:
        print(f"{path} is out of date: run python -m cast.config.schema_gen --write", file=sys.stderr)
        return 1
    if not args.check:
        print(render(fresh))
    return 0


if __name__ == "__main__":
    sys.exit(main())
