"""docs/design.md is the design the repository cites, and what it shows is so; links between the docs resolve."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from cast.config import read_config
from tests.docs.pages import ROOT, blocks, fenced, section

DESIGN = "docs/design.md"
ORIGINAL = "DESIGN" + ".md"  # the original design, outside the repository: cited nowhere any more


def tracked_files() -> list[Path]:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [ROOT / name for name in out.split("\0") if name and (ROOT / name).is_file()]


def texts() -> dict[str, str]:
    found = {}
    for path in tracked_files():
        try:
            found[str(path.relative_to(ROOT))] = path.read_text()
        except UnicodeDecodeError:
            continue
    return found


def test_the_repository_cites_docs_design_md_and_never_the_original() -> None:
    sections = {int(n): title for n, title in re.findall(r"^## (\d+)\. (.+)$", (ROOT / DESIGN).read_text(), re.M)}
    assert sorted(sections) == list(range(1, len(sections) + 1)), sections
    original, bad, cited = [], [], 0
    for name, text in texts().items():
        if ORIGINAL in text:
            original.append(name)
        for number in re.findall(r"design\.md,? sections? (\d+)", text):
            cited += 1
            if int(number) not in sections:
                bad.append(f"{name}: section {number}")
    assert not original, f"these cite the original {ORIGINAL}; cite docs/design.md instead: {original}"
    assert not bad, f"citations of sections docs/design.md does not have: {bad}"
    assert cited >= 10


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def test_links_between_the_docs_resolve() -> None:
    pages = [ROOT / "README.md", ROOT / "java_client" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    broken = []
    for page in pages:
        text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.M | re.S)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            goal = (page.parent / path).resolve() if path else page
            if not goal.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such file)")
                continue
            if anchor and goal.suffix == ".md":
                anchors = {github_anchor(h) for h in re.findall(r"^#+ (.+)$", goal.read_text(), re.M)}
                if anchor not in anchors:
                    broken.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, broken


def test_the_readme_links_the_language_pages_and_the_design() -> None:
    readme = (ROOT / "README.md").read_text()
    for page in ("docs/python.md", "docs/cpp.md", "docs/java.md", DESIGN):
        assert f"]({page})" in readme, f"the README does not link {page}"


def test_the_folders_named_are_there() -> None:
    (tree,) = [t for t in fenced(section(DESIGN, "2. The parts"), "text") if not t.startswith("role ")]
    missing, top = [], None
    for line in tree.splitlines():
        if not line.startswith(" "):
            top = line.split()[0]
            if not (ROOT / top).exists():
                missing.append(top)
        assert top is not None
        # Sub-folders named in a description (`core/`, `cpp/segmenter`) are below the folder described,
        # or named from the root (`docs/performance.md`).
        description = line if line.startswith(" ") else line.split(None, 1)[1]
        for sub in re.findall(r"(?<![\w/.])([a-z][\w-]*/[\w/.-]*)", description):
            if not (ROOT / top / sub).exists() and not (ROOT / sub).exists():
                missing.append(f"{top}{sub}")
    assert not missing, missing


def test_the_folders_name_every_package_and_test_suite() -> None:
    (tree,) = [t for t in fenced(section(DESIGN, "2. The parts"), "text") if not t.startswith("role ")]
    text = " ".join(tree.split())
    packages = [p.name for p in (ROOT / "python" / "cast").iterdir()
                if p.is_dir() and (p / "__init__.py").exists() and p.name != "v1"]
    suites = [p.name for p in (ROOT / "tests").iterdir() if p.is_dir() and any(p.glob("test_*.py"))]
    assert [p for p in packages if f"{p}/" not in text] == [], "packages the folder list does not name"
    assert [s for s in suites if s not in text] == [], "test suites the folder list does not name"


def test_the_client_file_map_is_there() -> None:
    (table,) = [t for t in fenced(section(DESIGN, "2. The parts"), "text") if t.startswith("role ")]
    header, *rows = table.strip().splitlines()
    roots = header.split()[1:]
    assert roots == ["python/cast/client/", "cpp_client/", "java_client/src/main/java/cast/client/"]
    assert [row.split()[0] for row in rows] == [
        "component", "transport", "grpc_transport", "write_stream", "watch_stream", "session", "conversions",
        "credentials"]
    missing = [f"{root}{name}" for row in rows for root, name in zip(roots, row.split()[1:], strict=True)
               if not (ROOT / root / name).is_file()]
    assert not missing, missing


def test_the_configuration_shown_is_the_demos() -> None:
    (shown,) = [b.code for b in blocks(DESIGN) if b.lang == "yaml"]
    # Read as if it were a file next to the demo's, so that relative paths mean the same.
    config, problems = read_config(ROOT / "configs" / "shown.yaml", environ={}, text=shown)
    demo, demo_problems = read_config(ROOT / "configs" / "demo.yaml", environ={})
    assert config is not None and not problems.items, [str(p) for p in problems.items]
    assert demo is not None and not demo_problems.items

    def shape(c: object) -> dict[str, tuple[object, ...]]:
        return {
            comp.id: (comp.subarchitecture, comp.language, comp.kind, comp.cls, comp.run, comp.privileged,
                      comp.classpath)
            for comp in c.components  # type: ignore[attr-defined]
        }

    assert shape(config) == shape(demo)
    assert {n: (sa.policy, sa.policy_options) for n, sa in config.subarchitectures.items()} == {
        n: (sa.policy, sa.policy_options) for n, sa in demo.subarchitectures.items()
    }
    assert config.python_path == demo.python_path


TEST_REFERENCE = re.compile(r"`((?:tests/)?[a-z0-9_]+(?:/[a-z0-9_]+)*\.py)::([A-Za-z0-9_]+)")


def test_every_test_the_docs_name_exists() -> None:
    """A guarantee's table row names the test that checks it (`dir/file.py::test_name`, under tests/):
    that file must define that test, so renaming or moving a test cannot leave a claim without one."""
    missing, named = [], 0
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for path, name in TEST_REFERENCE.findall(doc.read_text()):
            named += 1
            # A bare file name (a page about one suite, e.g. reliability.md) is the one file of that name.
            relative = path.removeprefix("tests/")
            files = [ROOT / "tests" / relative] if "/" in relative else sorted((ROOT / "tests").rglob(relative))
            if not any(file.is_file() and re.search(rf"^\s*(?:async )?def {name}\(|^class {name}\b",
                                                    file.read_text(), re.M) for file in files):
                missing.append(f"{doc.relative_to(ROOT)}: {path}::{name}")
    assert named >= 50, named  # the pattern still finds the tables
    assert not missing, "tests named in the docs that do not exist:\n" + "\n".join(missing)


def test_every_test_file_the_docs_and_the_code_name_exists() -> None:
    """A path under tests/ named in a page or in the product's own text is a file of the repository."""
    pattern = re.compile(r"\btests/[A-Za-z0-9_/]+\.(?:py|cc|java)\b")
    missing = sorted({f"{name}: {path}" for name, text in texts().items()
                      if not name.startswith("tests/") and name != "CHANGELOG.md"
                      for path in pattern.findall(text)
                      if not any((ROOT / base / path).is_file() for base in ("", "cpp_client", "java_client"))})
    assert not missing, "files under tests/ that are named but do not exist:\n" + "\n".join(missing)
