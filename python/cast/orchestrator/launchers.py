"""How a component of each language is started: the launcher registry.

Every launcher turns a :class:`ComponentConfig` into a command line; the
orchestrator adds the launch contract (``CAST_ENDPOINT``, ``CAST_TOKEN``, ...)
to the environment. The conventions are fixed so that the C++ and Java runners
plug in without changes here:

- python: ``<this python> -m cast.run module:Class``, with the configuration's
  ``python_path`` entries first on ``PYTHONPATH``;
- cpp: the ``run:`` executable: an absolute path, a path relative to the file
  that names it, or a bare name looked up in ``$CAST_CPP_BIN_DIR`` (default
  ``<repo>/build/cpp/bin``), then ``PATH``;
- java: ``java -cp <classpath> cast.client.Runner <class>``, the class path being
  ``$CAST_JAVA_CLASSPATH`` (default ``<repo>/java_client/target/cast-client-all.jar``)
  plus the component's ``classpath:`` entries; ``java`` is ``$JAVA_HOME/bin/java``
  if set, else found on ``PATH``.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Protocol

from cast.config.model import ComponentConfig, SystemConfig
from cast.errors import NotFoundError

__all__ = [
    "LAUNCHERS",
    "REPO_ROOT",
    "CppLauncher",
    "JavaLauncher",
    "LaunchError",
    "Launcher",
    "PythonLauncher",
    "launcher_for",
    "register_launcher",
]

# python/cast/orchestrator/launchers.py -> the repository (for an editable install, where builds live).
REPO_ROOT = Path(__file__).resolve().parents[3]
JAVA_RUNNER = "cast.client.Runner"


class LaunchError(NotFoundError):
    """A component cannot be started: its executable, runtime or build is missing."""


class Launcher(Protocol):
    """Starts components of one language."""

    def command(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> list[str]:
        """The command line; :class:`LaunchError` saying what to build or install if it cannot run."""

    def environment(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> dict[str, str]:
        """Variables to add to the component's environment (besides the launch contract)."""


class PythonLauncher:
    """``python -m cast.run module:Class``."""

    def command(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> list[str]:
        """This interpreter running the Python runner."""
        return [sys.executable, "-m", "cast.run", component.cls]

    def environment(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> dict[str, str]:
        """``PYTHONPATH`` with the configuration's ``python_path`` first."""
        parts = [str(p) for p in config.python_path]
        if env.get("PYTHONPATH"):
            parts.append(env["PYTHONPATH"])
        # Unbuffered, so that output reaches the log files and the status view line by line.
        return {"PYTHONPATH": os.pathsep.join(parts), "PYTHONUNBUFFERED": "1"} if parts else {"PYTHONUNBUFFERED": "1"}


def cpp_bin_dir(env: Mapping[str, str]) -> Path:
    """Where bare ``run:`` names are looked up first."""
    return Path(env.get("CAST_CPP_BIN_DIR") or REPO_ROOT / "build" / "cpp" / "bin")


class CppLauncher:
    """The component's own executable (linked against the C++ client library)."""

    def command(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> list[str]:
        """The resolved ``run:`` executable."""
        return [str(self.resolve(component, env))]

    def resolve(self, component: ComponentConfig, env: Mapping[str, str]) -> Path:
        """The executable's path; LaunchError if there is none."""
        run = component.run
        if os.sep in run or (os.altsep and os.altsep in run):
            path = Path(run) if Path(run).is_absolute() else component.base_dir / run
            if not (path.is_file() and os.access(path, os.X_OK)):
                raise LaunchError(f"component '{component.id}': executable '{path}' does not exist or is not "
                                  "executable: build it first (make cpp)")
            return path
        bin_dir = cpp_bin_dir(env)
        candidate = bin_dir / run
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return candidate
        found = shutil.which(run, path=env.get("PATH"))
        if found:
            return Path(found)
        raise LaunchError(f"component '{component.id}': executable '{run}' is not in {bin_dir} "
                          "($CAST_CPP_BIN_DIR) nor on PATH: build the C++ components first (make cpp)")

    def environment(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> dict[str, str]:
        """Nothing beyond the launch contract."""
        return {}


class JavaLauncher:
    """``java -cp <classpath> cast.client.Runner <class>``."""

    def classpath(self, component: ComponentConfig, env: Mapping[str, str]) -> list[str]:
        """The class path entries, the client library's first."""
        base = env.get("CAST_JAVA_CLASSPATH")
        default = REPO_ROOT / "java_client" / "target" / "cast-client-all.jar"
        entries = base.split(os.pathsep) if base else [str(default)]
        return [*entries, *component.classpath]

    def java(self, env: Mapping[str, str]) -> str:
        """The java executable."""
        home = env.get("JAVA_HOME")
        if home and (Path(home) / "bin" / "java").is_file():
            return str(Path(home) / "bin" / "java")
        found = shutil.which("java", path=env.get("PATH"))
        if not found:
            raise LaunchError("no 'java' executable: install a JDK (17 or newer) or set JAVA_HOME")
        return found

    def command(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> list[str]:
        """The JVM running the Java runner."""
        classpath = self.classpath(component, env)
        missing = [e for e in classpath if not e.endswith("*") and not Path(e).exists()]
        if missing:
            # Say which build is missing: the client library, or the component's own jar.
            client = [e for e in missing if e not in component.classpath]
            hint = (
                "build the Java client first (make java) or set CAST_JAVA_CLASSPATH"
                if client
                else "build the component's jar (for the demo's: make java-demo)"
            )
            raise LaunchError(f"component '{component.id}': class path entries missing: {', '.join(missing)}: {hint}")
        return [self.java(env), "-cp", os.pathsep.join(classpath), JAVA_RUNNER, component.cls]

    def environment(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> dict[str, str]:
        """Nothing beyond the launch contract."""
        return {}


LAUNCHERS: dict[str, Launcher] = {"python": PythonLauncher(), "cpp": CppLauncher(), "java": JavaLauncher()}


def register_launcher(language: str, launcher: Launcher) -> None:
    """Add or replace the launcher of a language."""
    LAUNCHERS[language] = launcher


def launcher_for(language: str) -> Launcher:
    """The launcher of a language; LaunchError if none is registered."""
    launcher = LAUNCHERS.get(language)
    if launcher is None:
        raise LaunchError(f"no launcher for language '{language}' (known: {', '.join(LAUNCHERS)})")
    return launcher
