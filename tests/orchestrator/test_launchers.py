"""Launcher errors say which build is missing."""

from __future__ import annotations

from pathlib import Path

import pytest

from cast.config import ComponentConfig
from cast.orchestrator.launchers import LAUNCHERS, LaunchError


def java_component(classpath: list[str]) -> ComponentConfig:
    return ComponentConfig("colour", "vision", language="java", kind="managed", cls="x.Colour", classpath=classpath)


def test_missing_component_jar_points_at_the_components_build(tmp_path: Path) -> None:
    client = tmp_path / "cast-client-all.jar"
    client.write_bytes(b"")
    component = java_component([str(tmp_path / "missing-demo.jar")])
    hint = r"missing-demo\.jar: build the component's jar \(for the demo's: make java-demo\)"
    with pytest.raises(LaunchError, match=hint):
        LAUNCHERS["java"].command(component, None, {"CAST_JAVA_CLASSPATH": str(client), "PATH": ""})  # type: ignore[arg-type]


def test_missing_client_jar_points_at_make_java(tmp_path: Path) -> None:
    component = java_component([])
    with pytest.raises(LaunchError, match=r"build the Java client first \(make java\)"):
        LAUNCHERS["java"].command(component, None, {"CAST_JAVA_CLASSPATH": str(tmp_path / "no.jar"), "PATH": ""})  # type: ignore[arg-type]
