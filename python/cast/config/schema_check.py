"""Checking a configuration tree against the JSON Schema, each problem on its file and line.

``jsonschema`` decides what is wrong; this module says where (the tree of
:mod:`cast.config.source` remembers the position of every key and value) and
in ``cast check``'s words: ``unknown key 'clas' (did you mean 'class'?)``,
``must be true or false, not 'maybe'``, ``'rust' is not one of python, cpp,
java, other``. A schema node may give its own words in ``errorMessage`` (the
keyword VS Code and yaml-language-server show too); the value is added to them
(``, not a mapping`` after a wrong type, ``'nowhere' `` before a pattern).

Every value found wrong is removed from the tree, so that the builder after it
sees valid values or nothing (and takes the default), and reports each mistake
once. Unions (``anyOf``) are told apart by type: a value is explained by the
branch of its own type, so ``restart: sometimes`` is "not one of never, ...".
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any

from jsonschema import Draft7Validator, ValidationError
from jsonschema.protocols import Validator
from jsonschema.validators import extend

from cast.config.problems import Position, Problems, closest, did_you_mean
from cast.config.schema import mapping_properties, resolve
from cast.config.source import YList, YMap

__all__ = ["Path", "check_tree", "describe", "dotted"]

Path = tuple[str | int, ...]

# YAML tells 2 from 2.0, and cast check always refused 2.0 where a whole number is asked for; JSON Schema's
# "integer" would take 2.0, so the validator counts only ints (never bools) as integers.
_TYPES = Draft7Validator.TYPE_CHECKER.redefine(
    "integer", lambda _checker, value: isinstance(value, int) and not isinstance(value, bool)
)
_StrictDraft7: Any = extend(Draft7Validator, type_checker=_TYPES)  # type: ignore[no-untyped-call]  # stubs: untyped
_SCALAR_TYPES = {"boolean", "integer", "number"}


def validator_for(schema: Mapping[str, Any]) -> Validator:
    """A draft-07 validator for ``schema`` that refuses 2.0 as a whole number (as cast check does)."""
    validator: Validator = _StrictDraft7(schema)
    return validator


def check_tree(
    tree: YMap, schema: Mapping[str, Any], problems: Problems, base: Path = ()
) -> set[Path]:
    """Add a problem for each place ``tree`` breaks ``schema``, remove the values found wrong, return their paths.

    ``base`` is the path of ``tree`` in the whole configuration (for the keys in messages).
    """
    found: dict[tuple[Position, str, str], None] = {}  # one line per mistake, in the order found
    remove: set[Path] = set()
    for error in validator_for(schema).iter_errors(tree):
        for pos, path, message, wrong in _explain(error, tree, schema):
            found[(pos, dotted(base + path), message)] = None
            if wrong is not None:
                remove.add(wrong)
    for pos, key, message in found:
        problems.error(pos, key, message)
    for path in sorted(remove, key=_order, reverse=True):  # children before parents, last list items first
        _remove(tree, path)
    return {base + path for path in remove}


_Explained = tuple[Position, Path, str, Path | None]


def _explain(error: ValidationError, tree: YMap, schema: Mapping[str, Any]) -> Iterator[_Explained]:
    """(position, key path, message, path to remove) for one jsonschema error."""
    path: Path = tuple(error.absolute_path)
    node: Mapping[str, Any] = error.schema if isinstance(error.schema, Mapping) else {}
    kind = error.validator
    value: Any = error.instance
    rule: Any = error.validator_value
    if list(error.absolute_schema_path)[-2:-1] == ["propertyNames"]:
        name = str(value)
        own = node.get("errorMessage", f"must match {node.get('pattern')}")
        message = f"{node.get('title', 'name')} '{name}' {own}"
        yield _key_pos(tree, (*path, name)), (*path, name), message, (*path, name)
    elif kind == "additionalProperties":
        allowed = set(mapping_properties(node, schema))
        for key in value:
            if key not in allowed:
                message = f"unknown key '{key}'{did_you_mean(key, allowed)}"
                yield _key_pos(tree, (*path, key)), (*path, key), message, (*path, key)
    elif kind == "required":
        props = mapping_properties(node, schema)
        for key in rule:
            if key not in value:
                own = resolve(props.get(key, {}), schema).get("errorMessage", f"missing: write '{key}:'")
                yield _key_pos(tree, path), (*path, key), own, None
    elif kind == "dependencies":
        for given, needed in rule.items():
            for key in needed if given in value else ():
                if key not in value:
                    mutual = given in rule.get(key, ())
                    message = (f"give {' and '.join(sorted((given, key)))} together, or neither" if mutual
                               else f"'{given}' needs '{key}' too")
                    yield _key_pos(tree, (*path, given)), (*path, key), message, None
    elif kind == "anyOf":
        branch = _branch_of(value, rule, schema)
        if branch is None:
            yield _value_pos(tree, path), path, _wrong_type(node, value, schema), path
        else:
            for sub in error.context or ():
                if sub.relative_schema_path and sub.relative_schema_path[0] == branch:
                    yield from _explain(sub, tree, schema)
    elif kind == "enum":
        if isinstance(value, (dict, list, bool)):
            yield _value_pos(tree, path), path, f"must be a word or text, not {describe(value)}", path
        else:
            words = [str(w) for w in rule if w is not None]
            message = f"'{value}' is not one of {', '.join(words)}{closest(str(value), words)}"
            yield _value_pos(tree, path), path, message, path
    elif kind in ("type", "minimum", "maximum"):
        yield _value_pos(tree, path), path, _wrong_type(node, value, schema), path
    elif kind == "pattern":
        own = node.get("errorMessage", f"must match {node.get('pattern')}")
        yield _value_pos(tree, path), path, f"'{value}' {own}", path
    elif kind in ("minLength", "minItems", "minProperties"):
        yield _value_pos(tree, path), path, str(node.get("errorMessage", "must not be empty")), path
    elif kind == "not":
        yield _key_pos(tree, path), path, str(node.get("errorMessage", "is not allowed here")), path
    else:  # a keyword this schema does not use today: jsonschema's own words
        yield _value_pos(tree, path), path, error.message, path


def _wrong_type(node: Mapping[str, Any], value: Any, schema: Mapping[str, Any]) -> str:
    """``must be ..., not X`` for a value of the wrong type (or below its minimum)."""
    types = set(_types(node, schema)) - {"null"}
    if "errorMessage" in node:
        phrase = str(node["errorMessage"])
    elif types == {"object"}:
        phrase = "must be a mapping"
    elif "string" in types:
        phrase = "must be a word or text"
    elif types == {"boolean"}:
        phrase = "must be true or false"
    elif types == {"integer"} and node.get("minimum") == 1:
        phrase = "must be a positive whole number"
    elif types <= {"integer", "number"} and types:
        phrase = "must be a whole number" if types == {"integer"} else "must be a number"
        if "minimum" in node:
            phrase += f" >= {node['minimum']:g}"
    elif types == {"array"}:
        phrase = "must be a list"
    else:
        phrase = f"must be {' or '.join(sorted(types))}"
    # A true/false or number setting shows the value as written ('maybe', -2); others say what it is.
    shown = repr(value) if types and types <= _SCALAR_TYPES and not isinstance(value, (dict, list)) else None
    return f"{phrase}, not {shown if shown is not None else describe(value)}"


def _types(node: Mapping[str, Any], schema: Mapping[str, Any]) -> list[str]:
    """The JSON types a schema node admits (through ``$ref`` and ``allOf``); empty if it does not say."""
    node = resolve(node, schema)
    declared = node.get("type")
    if declared is not None:
        return [declared] if isinstance(declared, str) else list(declared)
    out: list[str] = []
    for part in node.get("allOf", []):
        out += _types(part, schema)
    return out


def _json_type(value: Any) -> str | None:
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    for python, name in ((float, "number"), (str, "string"), (dict, "object"), (list, "array")):
        if isinstance(value, python):
            return name
    return "null" if value is None else None


def _branch_of(value: Any, branches: Iterable[Mapping[str, Any]], schema: Mapping[str, Any]) -> int | None:
    """The index of the ``anyOf`` branch for the value's type, or None if no branch takes that type."""
    kind = _json_type(value)
    for index, branch in enumerate(branches):
        types = _types(branch, schema)
        if kind in types or (kind == "integer" and "number" in types):
            return index
    return None


def describe(value: Any) -> str:
    """What a YAML value is, for messages: ``a mapping``, ``a list``, ``empty``, ``int 5``."""
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    if value is None:
        return "empty"
    return f"{type(value).__name__} {value!r}"


def dotted(path: Path) -> str:
    """The key of a path as messages write it: ``servers.main.subarchitectures`` (list indexes left out)."""
    return ".".join(str(step) for step in path if not isinstance(step, int))


def _parent(tree: YMap, path: Path) -> Any:
    node: Any = tree
    for step in path[:-1]:
        node = node[step]
    return node


def _value_pos(tree: YMap, path: Path) -> Position:
    if not path:
        return tree.pos
    parent = _parent(tree, path)
    if isinstance(parent, YList):
        return parent.item_pos[int(path[-1])]
    return parent.value_at(str(path[-1])) if isinstance(parent, YMap) else tree.pos


def _key_pos(tree: YMap, path: Path) -> Position:
    """Where the key of ``path`` is written (a list item: the item; the top level: the file's start)."""
    if not path:
        return tree.pos
    parent = _parent(tree, path)
    if isinstance(parent, YList):
        return parent.item_pos[int(path[-1])]
    return parent.at(str(path[-1])) if isinstance(parent, YMap) else tree.pos


def _order(path: Path) -> tuple[tuple[int, int, str], ...]:
    return tuple((0, step, "") if isinstance(step, int) else (1, 0, step) for step in path)


def _remove(tree: YMap, path: Path) -> None:
    try:
        parent = _parent(tree, path)
    except (KeyError, IndexError, TypeError):  # under a value removed already
        return
    if isinstance(parent, YList) and isinstance(path[-1], int) and path[-1] < len(parent):
        del parent[path[-1]]
        del parent.item_pos[path[-1]]
    elif isinstance(parent, YMap):
        parent.pop(str(path[-1]), None)
