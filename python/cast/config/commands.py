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
    """``run:`` as written (text) and, for ``other``, as the words of the command; problems added to ``problems``.

    The schema has already refused a ``run:`` that is no command line (a mapping, a word that is not text);
    what each language needs of it is checked here.
    """
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
    if isinstance(value, YList):
        if language == "cpp":
            problems.error(raw.value_at("run"), key,
                           "a cpp component's run: is one executable (a path or a name), not a list; "
                           "for a command line with arguments use language: other")
        return "", []  # not used by this language
    run = "" if value is None else str(value)
    if language == "cpp" and not run:
        problems.error(pos, key, CPP_NEEDS_RUN)
    return run, []


def _words(raw: YMap, key: str, problems: Problems) -> list[str] | None:
    """The command's words; None (a problem recorded) if ``run:`` cannot be split into words."""
    value = raw.get("run")
    if value is None:
        return []
    if isinstance(value, YList):
        return [str(item) for item in value]
    try:
        return shlex.split(str(value))
    except ValueError as exc:
        # shlex says "No closing quotation" or "No escaped character": say what to change.
        problems.error(raw.value_at("run"), key,
                       f"cannot split {str(value)!r} into words ({exc}): close the quote, or write run: as a "
                       "list of words")
        return None
