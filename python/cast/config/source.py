"""Reading configuration YAML with positions, variables and includes.

The result is a tree of :class:`YMap` / :class:`YList` / scalars that
remembers where every key and value was written (file, line), so that the
validator can name the line of each problem, also inside included files.

Variables: ``${NAME}`` and ``${NAME:-default}`` in any scalar (keys too).
Values come, first match wins, from ``--set NAME=value``, the environment,
the ``variables:`` section of the file (then of the files it includes), and
finally the inline default. ``$${`` writes a literal ``${``. A value that is
one variable (``${N:-2}``, or ``"${N:-2}"`` as flow mappings need) is typed
after substitution, so it is the number 2; quoted text around a variable
(``"n=${N}"``) stays a string.

Includes: ``include: other.yaml`` or a list of files, relative to the
including file (variables allowed in the paths). Included files are merged
in order, then the including file over them: mappings merge key by key,
anything else (scalars, lists) is replaced.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from yaml.constructor import ConstructorError, SafeConstructor
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode
from yaml.resolver import Resolver

from cast.config.problems import Position, Problems

__all__ = ["SourceTree", "Variables", "YList", "YMap", "load_tree", "position_of"]

_VAR = re.compile(r"\$\$\{|\$\{([^}:]*)(:-([^}]*))?\}")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_MERGE_TAG = "tag:yaml.org,2002:merge"


class YMap(dict[str, Any]):
    """A mapping read from YAML, with the position of itself, of each key and of each value."""

    def __init__(self, pos: Position) -> None:
        super().__init__()
        self.pos = pos
        self.key_pos: dict[str, Position] = {}
        self.value_pos: dict[str, Position] = {}

    def at(self, key: str) -> Position:
        """Where ``key`` is written (the mapping itself if absent)."""
        return self.key_pos.get(key, self.pos)

    def value_at(self, key: str) -> Position:
        """Where the value of ``key`` is written."""
        return self.value_pos.get(key, self.at(key))


class YList(list[Any]):
    """A sequence read from YAML, with the position of itself and of each item."""

    def __init__(self, pos: Position) -> None:
        super().__init__()
        self.pos = pos
        self.item_pos: list[Position] = []


def position_of(file: str, node: Node) -> Position:
    """The 1-based position of a YAML node."""
    mark = node.start_mark
    return Position(file, mark.line + 1, mark.column + 1)


@dataclass
class Variables:
    """Where variable values come from, in order of precedence."""

    overrides: Mapping[str, str] = field(default_factory=dict)
    environ: Mapping[str, str] = field(default_factory=lambda: dict(os.environ))
    file_values: dict[str, str] = field(default_factory=dict)
    used: dict[str, str] = field(default_factory=dict)

    def lookup(self, name: str) -> str | None:
        """The value of a variable, or None if it is set nowhere."""
        for source in (self.overrides, self.environ, self.file_values):
            if name in source:
                return source[name]
        return None


@dataclass
class SourceTree:
    """A loaded configuration: its merged tree, the files read, and the problems found."""

    root: YMap
    files: list[Path]
    problems: Problems
    variables: Variables
    readable: bool = True


class _Reader:
    def __init__(self, variables: Variables, problems: Problems) -> None:
        self.vars = variables
        self.problems = problems
        self.files: list[Path] = []
        self._constructor = SafeConstructor()
        self._resolver = Resolver()

    # ------------------------------------------------------------ variables

    def substitute(self, text: str, pos: Position, key: str) -> str:
        def replace(m: re.Match[str]) -> str:
            if m.group(0) == "$${":
                return "${"
            name, has_default, default = m.group(1), m.group(2), m.group(3)
            if not _NAME.match(name):
                self.problems.error(pos, key, f"bad variable '{m.group(0)}': write ${{NAME}} or ${{NAME:-default}}")
                return ""
            value = self.vars.lookup(name)
            if value is None or (value == "" and has_default):
                if has_default is None:
                    self.problems.error(
                        pos,
                        key,
                        f"variable '{name}' is not set: set it with --set {name}=VALUE, in the environment, in "
                        f"'variables:', or give a default as ${{{name}:-VALUE}}",
                    )
                    return ""
                value = default or ""
            self.vars.used[name] = value
            return value

        return _VAR.sub(replace, text)

    # ----------------------------------------------------------- conversion

    def scalar(self, file: str, node: ScalarNode, key: str) -> Any:
        pos = position_of(file, node)
        if "$" in node.value and _VAR.search(node.value):
            text = self.substitute(node.value, pos, key)
            whole = _VAR.fullmatch(node.value) is not None and node.value != "$${"
            if node.style is not None and not whole:  # quoted text around a variable: stays a string
                return text
            tag = self._resolver.resolve(ScalarNode, text, (True, False))  # type: ignore[no-untyped-call]
            node = ScalarNode(tag, text, node.start_mark, node.end_mark)
        try:
            return self._constructor.construct_object(node, deep=True)
        except ConstructorError as exc:
            self.problems.error(pos, key, f"cannot read value: {exc.problem}")
            return None

    def convert(self, file: str, node: Node, key: str) -> Any:
        if isinstance(node, ScalarNode):
            return self.scalar(file, node, key)
        if isinstance(node, SequenceNode):
            out = YList(position_of(file, node))
            for i, item in enumerate(node.value):
                out.append(self.convert(file, item, f"{key}[{i}]"))
                out.item_pos.append(position_of(file, item))
            return out
        if isinstance(node, MappingNode):
            return self.mapping(file, node, key)
        return None

    def mapping(self, file: str, node: MappingNode, key: str, skip: frozenset[str] = frozenset()) -> YMap:
        out = YMap(position_of(file, node))
        merged: list[YMap] = []
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                sources = value_node.value if isinstance(value_node, SequenceNode) else [value_node]
                for src in sources:
                    if isinstance(src, MappingNode):
                        merged.append(self.mapping(file, src, key))
                continue
            kpos = position_of(file, key_node)
            raw_key = self.convert(file, key_node, key) if isinstance(key_node, ScalarNode) else None
            if raw_key is None or isinstance(raw_key, (YMap, YList)):
                self.problems.error(kpos, key, "keys must be plain words")
                continue
            name = str(raw_key)
            if name in skip:
                continue
            path = f"{key}.{name}" if key else name
            if name in out:
                self.problems.error(
                    kpos, path, f"'{name}' is given twice (first at line {out.key_pos[name].line}); keep one"
                )
                continue
            out[name] = self.convert(file, value_node, path)
            out.key_pos[name] = kpos
            out.value_pos[name] = position_of(file, value_node)
        for src_map in merged:  # YAML merge keys: explicit keys win
            for name, value in src_map.items():
                if name not in out:
                    out[name] = value
                    out.key_pos[name] = src_map.key_pos[name]
                    out.value_pos[name] = src_map.value_pos[name]
        return out

    # --------------------------------------------------------------- files

    def load(self, path: Path, stack: tuple[Path, ...], at: Position | None, text: str | None = None) -> YMap | None:
        resolved = path.resolve()
        if resolved in stack:
            chain = " -> ".join(p.name for p in (*stack, resolved))
            self.problems.error(at or Position(str(path)), "include", f"files include each other in a cycle: {chain}")
            return None
        try:
            if text is None:
                text = path.read_text()
        except OSError as exc:
            where = at or Position(str(path))
            self.problems.error(where, "include" if at else "", f"cannot read '{path}': {exc.strerror}")
            return None
        self.files.append(path)
        file = str(path)
        try:
            node = yaml.compose(text, Loader=yaml.SafeLoader)
        except yaml.MarkedYAMLError as exc:
            mark = exc.problem_mark or exc.context_mark
            line = mark.line + 1 if mark is not None else 0
            column = mark.column + 1 if mark is not None else 0
            what = f"{exc.context}, {exc.problem}" if exc.context else str(exc.problem)
            self.problems.error(Position(file, line, column), "", f"invalid YAML: {what}")
            return None
        except yaml.YAMLError as exc:
            self.problems.error(Position(file), "", f"invalid YAML: {exc}")
            return None
        if node is None:
            return YMap(Position(file, 1))
        if not isinstance(node, MappingNode):
            self.problems.error(
                position_of(file, node), "", "the top level must be a mapping (system:, subarchitectures:, ...)"
            )
            return None
        entries = {str(k.value): (k, v) for k, v in node.value if isinstance(k, ScalarNode)}
        if "variables" in entries:
            self._variables(file, *entries["variables"])
        base: YMap | None = None
        if "include" in entries:
            for inc_path, inc_pos in self._include_paths(file, *entries["include"]):
                included = self.load(path.parent / inc_path, (*stack, resolved), inc_pos)
                if included is not None:
                    base = included if base is None else merge(base, included)
        own = self.mapping(file, node, "", skip=frozenset({"variables", "include"}))
        return own if base is None else merge(base, own)

    def _variables(self, file: str, key_node: Node, value_node: Node) -> None:
        value = self.convert(file, value_node, "variables")
        if value is None:
            return
        if not isinstance(value, YMap):
            self.problems.error(position_of(file, value_node), "variables", "must be a mapping of NAME: value")
            return
        for name, val in value.items():
            if not _NAME.match(name):
                self.problems.error(value.at(name), f"variables.{name}", "variable names are letters, digits and _")
            elif isinstance(val, (YMap, YList)):
                self.problems.error(value.at(name), f"variables.{name}", "a variable's value must be a scalar")
            else:
                # The including file was read first, so its values win over an included file's.
                self.vars.file_values.setdefault(name, "" if val is None else _text(val))

    def _include_paths(self, file: str, key_node: Node, value_node: Node) -> list[tuple[str, Position]]:
        value = self.convert(file, value_node, "include")
        items: list[tuple[Any, Position]]
        if isinstance(value, YList):
            items = list(zip(value, value.item_pos, strict=True))
        else:
            items = [(value, position_of(file, value_node))]
        out = []
        for item, pos in items:
            if not isinstance(item, str) or not item:
                self.problems.error(pos, "include", "must be a file name or a list of file names")
            else:
                out.append((item, pos))
        return out


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def merge(base: YMap, over: YMap) -> YMap:
    """``over`` merged onto ``base``: mappings merge key by key, other values are replaced."""
    out = YMap(over.pos)
    for src in (base, over):
        for name, value in src.items():
            old = out.get(name)
            if isinstance(old, YMap) and isinstance(value, YMap):
                value = merge(old, value)
            out[name] = value
            out.key_pos[name] = src.key_pos[name]
            out.value_pos[name] = src.value_pos[name]
    return out


def load_tree(
    path: str | os.PathLike[str],
    overrides: Mapping[str, str] | None = None,
    environ: Mapping[str, str] | None = None,
    text: str | None = None,
) -> SourceTree:
    """Read a configuration file (or ``text`` named ``path``) and its includes into one tree.

    Problems are collected in the result, not raised.
    """
    variables = Variables(dict(overrides or {}), dict(os.environ if environ is None else environ))
    problems = Problems()
    reader = _Reader(variables, problems)
    root = reader.load(Path(path), (), None, text)
    readable = root is not None
    tree = SourceTree(root if root is not None else YMap(Position(str(path))), reader.files, problems, variables)
    tree.readable = readable
    return tree
