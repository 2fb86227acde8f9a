"""Reading the code blocks of the documentation pages and the markers that say how each is tested.

A marker is an HTML comment on the line right before a block's opening fence:

- ``<!-- save NAME -->``: the block is written to NAME in the page's working directory, for the
  ``run`` blocks after it (a Python file must compile);
- ``<!-- run [as=ID] [sa=SA] [args=JSON] [main=module:Class] -->``: the block is run against a
  real server: a ``sh`` block with bash in the working directory (``cast`` on PATH,
  ``CAST_ENDPOINT`` and ``CAST_SECRET`` of the server); a Python, C++ or Java block with the
  launch environment of component ID (default ``notebook``) in SA (default ``vision``). It must
  exit 0;
- ``<!-- output -->``: what the ``run`` block before it prints on stdout, compared after
  normalising what changes from run to run (generated ids, versions, times);
- ``<!-- test -->``: the block is a test file of the testing kit (cast.testing, cast/testing.h,
  cast-testing), run by its language's test framework in the page's working directory: pytest,
  GoogleTest (compiled against the library `make cpp` built), JUnit 5 under Maven (on the
  artifacts `make java` installed). Every test in it must pass;
- ``<!-- file PATH -->`` / ``<!-- excerpt PATH -->``: the block is that file of the repository
  (without a first line that only points an editor at a JSON schema), or a part of it (whitespace
  aside); the page says which test builds or runs the file;
- ``<!-- tested-by tests/FILE.py::test_name -->``: another test runs or checks the block (that
  test's file must name the page);
- ``<!-- fragment -->``: not run: a piece of a larger whole, kept few.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# The pages whose every code block is tested.
PAGES = ("docs/python.md", "docs/cpp.md", "docs/java.md", "docs/design.md", "docs/ros.md")
KINDS = ("save", "run", "output", "test", "file", "excerpt", "tested-by", "fragment")
MAX_FRAGMENTS = 2

FENCE = re.compile(r"^```(?P<lang>[\w+-]*)\n(?P<code>.*?)^```[ \t]*$", re.M | re.S)
MARKER = re.compile(r"^<!--\s*(?P<kind>[\w-]+)(?P<rest>.*?)-->\s*$")


@dataclass
class Block:
    """One fenced code block of a page, with its marker."""

    page: str
    line: int
    lang: str
    code: str
    kind: str | None
    argument: str = ""
    attrs: dict[str, str] = field(default_factory=dict)

    @property
    def where(self) -> str:
        """``page:line`` of the opening fence."""
        return f"{self.page}:{self.line}"


def blocks(page: str) -> list[Block]:
    """Every fenced block of ``page`` (a path relative to the repository), in order."""
    text = (ROOT / page).read_text()
    found = []
    for match in FENCE.finditer(text):
        start = match.start()
        line = text.count("\n", 0, start) + 1
        previous = text[:start].rstrip("\n").rsplit("\n", 1)[-1] if start else ""
        marker = MARKER.match(previous) if text[:start].endswith("\n") and not text[:start].endswith("\n\n") else None
        kind, argument, attrs = None, "", {}
        if marker:
            kind = marker["kind"]
            rest = marker["rest"].strip()
            words = shlex.split(rest) if rest else []
            attrs = dict(w.split("=", 1) for w in words if "=" in w)
            argument = " ".join(w for w in words if "=" not in w)
        found.append(Block(page, line, match["lang"], match["code"], kind, argument, attrs))
    return found


def section(page: str, title: str) -> str:
    """The text of the ``## title`` section of a page."""
    text = (ROOT / page).read_text()
    start = text.index(f"## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end != -1 else None]


def fenced(text: str, lang: str) -> list[str]:
    """The contents of the ``lang`` code blocks in ``text``."""
    return re.findall(rf"^```{lang}\n(.*?)^```", text, re.M | re.S)


def normalise(output: str) -> list[str]:
    """Output lines with what changes from run to run replaced: generated ids, versions, times."""
    text = re.sub(r":[0-9a-f]{6}:", ":X:", output)
    text = re.sub(r"\bversion \d+", "version N", text)
    text = re.sub(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d+)?Z", "TIME", text)
    return [line.rstrip() for line in text.strip("\n").splitlines()]


def shown(path: str) -> str:
    """A file of the repository as a page shows it: without a first line that only points an editor at a schema."""
    text = (ROOT / path).read_text()
    first, _, rest = text.partition("\n")
    return rest if first.startswith("# yaml-language-server: $schema=") else text
