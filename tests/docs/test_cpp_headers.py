"""The C++ headers a user sees are the API that docs/cpp.md lists ("Headers"), and nothing internal.

``cpp_client/include/cast/*.h`` are the public headers, each in the page's list;
``include/cast/detail/`` holds only what public templates need in the user's code (installed, and
listed as not the API); the rest of the machinery is in ``cpp_client/src``, which is not installed.
A public header declares nothing in a ``detail`` namespace but forward declarations, and includes
only installed headers. That each header compiles on its own is checked by the build
(``cast_header_checks`` in ``cpp_client/tests/CMakeLists.txt``), which the last test keeps in place.
"""

from __future__ import annotations

import re
from pathlib import Path

from tests.docs.pages import ROOT, blocks

PAGE = "docs/cpp.md"
INCLUDE = ROOT / "cpp_client" / "include"
# A forward declaration: all a public header may put in a detail namespace.
FORWARD = re.compile(r"(class|struct)\s+\w+\s*;")


def documented() -> list[str]:
    """The headers docs/cpp.md lists in its "Headers" block, in order."""
    [block] = [b for b in blocks(PAGE)
               if b.kind == "tested-by" and b.argument.endswith("::test_the_headers_are_the_documented_ones")]
    return re.findall(r"^(cast/\S+\.h)\s", block.code, re.M)


def on_disk() -> list[str]:
    return sorted(str(p.relative_to(INCLUDE)) for p in INCLUDE.glob("cast/**/*.h")
                  if p.parent.name != "v1")  # cast/v1 is generated at build time, never in the tree


def public_headers() -> list[Path]:
    return sorted(INCLUDE.glob("cast/*.h"))


def without_comments(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def detail_blocks(text: str) -> list[str]:
    """The bodies of the ``namespace ...detail {`` blocks of a header (comments removed)."""
    code = without_comments(text)
    out = []
    for match in re.finditer(r"namespace\s+(?:[\w:]+::)?detail\s*\{", code):
        depth, at = 1, match.end()
        while depth and at < len(code):
            depth += {"{": 1, "}": -1}.get(code[at], 0)
            at += 1
        out.append(code[match.end():at - 1])
    return out


def test_the_headers_are_the_documented_ones() -> None:
    listed = documented()
    assert len(listed) == len(set(listed)), f"{PAGE} lists a header twice: {listed}"
    missing = sorted(set(on_disk()) - set(listed))
    gone = sorted(set(listed) - set(on_disk()))
    assert not missing, (f"cpp_client/include has headers {PAGE} does not list under \"Headers\": {missing}; "
                         "document a public one there, or keep an internal one in cpp_client/src")
    assert not gone, f"{PAGE} lists headers that cpp_client/include does not have: {gone}"
    internal = [h for h in listed if h.startswith("cast/detail/")]
    assert internal and all("not the API" in line for line in (ROOT / PAGE).read_text().splitlines()
                            if any(line.startswith(h) for h in internal)), \
        f"{PAGE} must say of each header in cast/detail that it is not the API"


def test_public_headers_define_nothing_in_a_detail_namespace() -> None:
    offences = []
    for header in public_headers():
        for body in detail_blocks(header.read_text()):
            rest = FORWARD.sub("", body).strip()
            if rest:
                offences.append(f"{header.relative_to(ROOT)}: {' '.join(rest.split())[:120]}")
    assert not offences, ("public headers define internal names (move them to include/cast/detail/ if a "
                          f"public template needs them in the user's code, else to cpp_client/src): {offences}")


def test_headers_include_only_installed_headers() -> None:
    offences = []
    for header in sorted(INCLUDE.glob("cast/**/*.h")):
        for name in re.findall(r'^\s*#\s*include\s+"([^"]+)"', header.read_text(), re.M):
            if not (INCLUDE / name).is_file():
                offences.append(f"{header.relative_to(ROOT)} includes \"{name}\"")
    assert not offences, f"installed headers include headers that are not installed: {offences}"


def test_the_build_compiles_every_header_on_its_own() -> None:
    cmake = (ROOT / "cpp_client" / "tests" / "CMakeLists.txt").read_text()
    assert re.search(r'file\(GLOB CAST_HEADERS[^)]*"\$\{CAST_INCLUDE_DIR\}/cast/\*\.h"\s+'
                     r'"\$\{CAST_INCLUDE_DIR\}/cast/detail/\*\.h"\)', cmake), \
        "cpp_client/tests/CMakeLists.txt no longer compiles each header of include/cast on its own"
    assert "add_library(cast_header_checks OBJECT ${CAST_HEADER_UNITS})" in cmake
