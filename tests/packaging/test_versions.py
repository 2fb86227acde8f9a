"""One release (the VERSION file) and one wire API (cast.v1), said the same everywhere (docs/compatibility.md)."""

from __future__ import annotations

import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib import metadata
from pathlib import Path

from cast.version import WIRE_API, library_version
from tests.conftest import ROOT

VERSION = (ROOT / "VERSION").read_text().strip()
POM = "{http://maven.apache.org/POM/4.0.0}"


def pom(path: str) -> ET.Element:
    return ET.parse(ROOT / path).getroot()


def dependency(root: ET.Element, artifact: str, managed: bool = False) -> ET.Element:
    where = f"{POM}dependencyManagement/{POM}dependencies" if managed else f"{POM}dependencies"
    for dep in root.iterfind(f"{where}/{POM}dependency"):
        if dep.findtext(f"{POM}artifactId") == artifact:
            return dep
    raise AssertionError(f"no dependency on {artifact}")


def test_version_file_is_one_release_number() -> None:
    assert re.fullmatch(r"\d+\.\d+\.\d+\n", (ROOT / "VERSION").read_text()), "VERSION: one line, MAJOR.MINOR.PATCH"


def test_the_wire_api_is_the_protobuf_package_of_every_proto_file() -> None:
    assert WIRE_API == "cast.v1"
    for proto in sorted((ROOT / "proto" / "cast" / "v1").glob("*.proto")):
        assert re.search(r"^package cast\.v1;$", proto.read_text(), re.M), f"{proto.name}: package is not cast.v1"


def test_python_reads_the_release_from_version() -> None:
    assert metadata.version("cast-grpc") == VERSION == library_version()
    out = subprocess.run([str(Path(sys.executable).parent / "cast"), "--version"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == f"cast {VERSION} (wire API cast.v1)", out


def test_cmake_reads_the_release_from_version() -> None:
    cmake = (ROOT / "cpp_client" / "CMakeLists.txt").read_text()
    assert 'file(STRINGS "${CMAKE_CURRENT_LIST_DIR}/../VERSION" CAST_VERSION LIMIT_COUNT 1)' in cmake
    assert "project(cast_cpp_client VERSION ${CAST_VERSION}" in cmake


def test_every_pom_names_the_release_in_version() -> None:
    # Maven takes a project's version before any plugin runs, so the poms write it: each must agree.
    bom = pom("java_client/bom/pom.xml")
    found = {
        "java_client/bom/pom.xml <version>": bom.findtext(f"{POM}version"),
        "java_client/pom.xml <parent><version>": pom("java_client/pom.xml").findtext(f"{POM}parent/{POM}version"),
        "examples/java/pom.xml cast-bom import": dependency(pom("examples/java/pom.xml"), "cast-bom", managed=True)
        .findtext(f"{POM}version"),
        "examples/java-demo/pom.xml cast-client": dependency(pom("examples/java-demo/pom.xml"), "cast-client")
        .findtext(f"{POM}version"),
    }
    wrong = {where: v for where, v in found.items() if v != VERSION}
    assert not wrong, f"these differ from VERSION ({VERSION}): {wrong}"
    # cast-client inherits its version and its grpc-java and protobuf versions from cast-bom.
    assert pom("java_client/pom.xml").find(f"{POM}version") is None
    protobuf = bom.findtext(f"{POM}properties/{POM}protobuf.version")
    assert pom("examples/java/pom.xml").findtext(f"{POM}properties/{POM}protobuf.version") == protobuf, (
        "examples/java generates its entry types with another protoc than the protobuf-java cast-bom pins")


def test_the_changelog_has_the_release() -> None:
    assert f"\n## {VERSION} " in (ROOT / "CHANGELOG.md").read_text()
