"""The product describes what is: no tracked file speaks of the project's work history.

A reader of the docs, the code, the tests or the bench output does not know the issues, rounds
and sessions in which the project was built, and should not need to: a heading names its subject,
a measurement keeps its date, commit and command. "Round trip", "around", "background" and a
component's session ("500 sessions", "the previous session") are words of the domain and pass.
"""

from __future__ import annotations

import re

from tests.docs.test_design import texts

# Built from pieces so that this file does not match its own pattern.
_DIGITS = "[0-9]"
HISTORY = re.compile(
    r"(?<![a-z])(?:"
    + "|".join(
        (
            rf"issues? ?#?{_DIGITS}+",  # a tracker's number, one or several ("issues N and M")
            rf"rounds? ?{_DIGITS}+\b",  # a round of work; "round trip" has no digit
            "round" + "2",  # the same glued to a name (a module, a function)
            rf"session[ -]{_DIGITS}+",  # a working session; "500 sessions" has the number first
        )
    )
    + ")",
    re.IGNORECASE,
)


def history_words(text: str) -> list[tuple[int, str]]:
    """(line number, matched words) of every line of ``text`` that speaks of work history."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        words = [m.group(0) for m in HISTORY.finditer(line)]
        if words:
            found.append((number, ", ".join(repr(w) for w in words)))
    return found


def test_the_pattern_tells_history_from_the_domain() -> None:
    history = [
        "Issue " + "7 bounds the slowdown",
        "(issue" + " #31)",
        "after issues " + "14 and 15",
        "## Round " + "2 in the full make bench",
        "bench/rows_round" + "2.py",
        "measured in session " + "7",
        "the session" + "-4 code",
    ]
    domain = [
        "one round trip each way",
        "in a round-trip time of around 2 ms",
        "three rounds of fresh servers",
        "p99 at 500 sessions 118036 µs",
        "Registering again ends the previous session.",
        "a background 5 s timer",
    ]
    assert [text for text in history if not history_words(text)] == []
    assert [text for text in domain if history_words(text)] == []


def test_no_tracked_file_speaks_of_work_history() -> None:
    files = texts()
    assert len(files) > 500, f"the walk found only {len(files)} tracked text files"
    found = [
        f"{name}:{number}: {words}" for name, text in sorted(files.items()) for number, words in history_words(text)
    ]
    assert not found, (
        f"{len(found)} line(s) speak of the project's work history (issue, round or session "
        "numbers); say what is instead: a heading names its subject, a measurement keeps its "
        "date, commit and command, a feature links its doc section:\n" + "\n".join(found)
    )
