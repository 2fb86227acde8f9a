"""The ``run:`` key of a component: one executable (cpp) or a command line (``language: other``).

A component of ``language: other`` is any program that speaks the gRPC API
itself (docs/client-protocol.md); ``run:`` is its command line, written as a
string (split into words the way a POSIX shell would, with :func:`shlex.split`:
quotes group, nothing is expanded) or as a list of words. Languages that do not
use ``run:`` ignore it, so one entry can switch language with a variable.
"""

from __future__ import annotations

import shlex

from cast.config.problems import Position, Problems
from cast.config.source import YList, YMap

__all__ = ["OTHER_NEEDS_RUN", "component_run"]

OTHER_NEEDS_RUN = (
    "an 'other' component needs 'run: COMMAND': its command line, as text ('node component.js') "
    "or a list of words ([node, component.js])"
)
CPP_NEEDS_RUN = "a cpp component needs 'run: EXECUTABLE' (a path, or a name looked up in $CAST_CPP_BIN_DIR, then PATH)"


def component_run(raw: YMap, language: str, pos: Position, where: str, problems: Problems) -> tuple[str, list[str]]:
    """``run:`` as written (text) and, for ``other``, as the words of the command; problems added to ``problems``."""
    key = f"{where}.run"
    value = raw.get("run")
    if language == "other":
        words = _words(raw, key, problems)
        if words is None:
            return "", []
        if not words:
            problems.error(raw.value_at("run") if "run" in raw else pos, key, OTHER_NEEDS_RUN)
            return "", []
        return (value if isinstance(value, str) else shlex.join(words)), words
    if isinstance(value, (YMap, YList)) or isinstance(value, bool):
        if language == "cpp":
            what = "a list" if isinstance(value, YList) else "a mapping" if isinstance(value, YMap) else repr(value)
            problems.error(raw.value_at("run"), key,
                           f"a cpp component's run: is one executable (a path or a name), not {what}; "
                           "for a command line with arguments use language: other")
        return "", []  # not used by this language
    run = "" if value is None else str(value)
    if language == "cpp" and not run:
        problems.error(pos, key, CPP_NEEDS_RUN)
    return run, []


def _words(raw: YMap, key: str, problems: Problems) -> list[str] | None:
    """The command's words; None (a problem recorded) if ``run:`` cannot be read as a command."""
    value = raw.get("run")
    if value is None:
        return []
    if isinstance(value, YList):
        words: list[str] = []
        for item, item_pos in zip(value, value.item_pos, strict=True):
            if isinstance(item, (YMap, YList)) or item is None:
                what = "empty" if item is None else "a list" if isinstance(item, YList) else "a mapping"
                problems.error(item_pos, key, f"each word of the command must be text, not {what}")
                return None
            words.append(str(item))
        return words
    if isinstance(value, YMap):
        problems.error(raw.value_at("run"), key, "must be a command line (text or a list of words), not a mapping")
        return None
    try:
        return shlex.split(str(value))
    except ValueError as exc:
        # shlex says "No closing quotation" or "No escaped character": say what to change.
        problems.error(raw.value_at("run"), key,
                       f"cannot split {str(value)!r} into words ({exc}): close the quote, or write run: as a "
                       "list of words")
        return None
