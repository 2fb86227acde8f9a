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
  if set, else found on ``PATH``;
- other: the ``run:`` command line, its first word resolved like cpp's ``run:``
  (but a bare name only on ``PATH``), run in the directory of the file that
  declares it so that relative paths among its arguments mean the same.

Launchers give the working directory too (None: the orchestrator's).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Protocol

from cast.config.model import ComponentConfig, SystemConfig
from cast.errors import NotFoundError
from cast.signals import STACK_DUMP_SIGNAL

__all__ = [
    "LAUNCHERS",
    "REPO_ROOT",
    "CppLauncher",
    "JavaLauncher",
    "LaunchError",
    "Launcher",
    "OtherLauncher",
    "PythonLauncher",
    "RosLauncher",
    "launcher_for",
    "register_launcher",
    "resolve_executable",
    "stack_dump_signal",
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

    def working_directory(self, component: ComponentConfig) -> Path | None:
        """Where the process starts (None: the orchestrator's working directory)."""


def stack_dump_signal(launcher: Launcher) -> int | None:
    """The signal on which the launcher's processes print their threads' stacks and carry on, if they have one.

    A launcher says so with a ``stack_dump_signal`` attribute (optional, so launchers registered before it
    existed still work); a stop that times out sends it before the SIGKILL, so the log says where it hung.
    """
    found = getattr(launcher, "stack_dump_signal", None)
    return found if isinstance(found, int) else None


class PythonLauncher:
    """``python -m cast.run module:Class``."""

    stack_dump_signal = STACK_DUMP_SIGNAL  # the runner registers faulthandler on it

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

    def working_directory(self, component: ComponentConfig) -> Path | None:
        """The orchestrator's."""
        return None


def cpp_bin_dir(env: Mapping[str, str]) -> Path:
    """Where bare ``run:`` names are looked up first."""
    return Path(env.get("CAST_CPP_BIN_DIR") or REPO_ROOT / "build" / "cpp" / "bin")


def resolve_executable(
    component: ComponentConfig, name: str, env: Mapping[str, str], hint: str, first: tuple[Path, str] | None = None
) -> Path:
    """``name`` as an executable file; :class:`LaunchError` ending with ``hint`` (what to do) if there is none.

    A name with a slash is a path (absolute, or relative to the component's
    file); a bare name is looked up in ``first`` (a directory and the variable
    that sets it), then on ``PATH``.
    """
    if os.sep in name or (os.altsep and os.altsep in name):
        path = Path(name) if Path(name).is_absolute() else component.base_dir / name
        if not (path.is_file() and os.access(path, os.X_OK)):
            raise LaunchError(f"component '{component.id}': executable '{path}' does not exist or is not "
                              f"executable: {hint}")
        return path
    if first is not None and (first[0] / name).is_file() and os.access(first[0] / name, os.X_OK):
        return first[0] / name
    found = shutil.which(name, path=env.get("PATH"))
    if found:
        return Path(found)
    searched = f"in {first[0]} ({first[1]}) nor on PATH" if first is not None else "on PATH"
    raise LaunchError(f"component '{component.id}': executable '{name}' is not {searched}: {hint}")


class CppLauncher:
    """The component's own executable (linked against the C++ client library)."""

    def command(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> list[str]:
        """The resolved ``run:`` executable."""
        return [str(self.resolve(component, env))]

    def resolve(self, component: ComponentConfig, env: Mapping[str, str]) -> Path:
        """The executable's path; LaunchError if there is none."""
        return resolve_executable(component, component.run, env, "build the C++ components first (make cpp)",
                                  (cpp_bin_dir(env), "$CAST_CPP_BIN_DIR"))

    def environment(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> dict[str, str]:
        """Nothing beyond the launch contract."""
        return {}

    def working_directory(self, component: ComponentConfig) -> Path | None:
        """The orchestrator's."""
        return None


class OtherLauncher:
    """A program in any language that speaks the gRPC API itself: the ``run:`` command line.

    It gets the launch contract like every component. It runs in the directory
    of the file that declares it, so that every relative path in the command
    line (the program's, and its arguments such as a script) is relative to
    that file, as the first word is for cpp's ``run:``.
    """

    def command(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> list[str]:
        """The command's words, the first resolved to an executable file."""
        if not component.command:
            raise LaunchError(f"component '{component.id}': no run: command to start")
        program, *arguments = component.command
        hint = "install it, or give its path in run: (relative paths are relative to the file that declares it)"
        return [str(resolve_executable(component, program, env, hint)), *arguments]

    def environment(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> dict[str, str]:
        """Nothing beyond the launch contract."""
        return {}

    def working_directory(self, component: ComponentConfig) -> Path | None:
        """The directory of the file that declares the component."""
        return component.base_dir


class JavaLauncher:
    """``java -cp <classpath> cast.client.Runner <class>``."""

    stack_dump_signal = STACK_DUMP_SIGNAL  # the JVM prints a thread dump on SIGQUIT and carries on

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

    def working_directory(self, component: ComponentConfig) -> Path | None:
        """The orchestrator's."""
        return None


class RosLauncher:
    """The ROS bridge: ``<interpreter with ROS> -m cast.run cast.bridges.ros.ros2:Ros2Bridge`` (or ``ros1:Ros1Bridge``).

    The interpreter is the one that has rclpy (ROS 2) or rospy (ROS 1) and the
    cast package: ``ros: python:`` (relative to the file, or a name on PATH),
    else ``$CAST_ROS2_PYTHON`` / this interpreter for ROS 2, ``$CAST_ROS1_PYTHON``
    / ``/usr/bin/python3`` (Debian's, the one rospy imports in) for ROS 1. Its
    ``ros:`` section travels as JSON in ``CAST_ROS_BRIDGE`` (docs/ros.md).
    """

    stack_dump_signal = STACK_DUMP_SIGNAL  # the Python runner's

    def python(self, component: ComponentConfig, env: Mapping[str, str]) -> str:
        """The interpreter that runs the bridge; LaunchError saying how to get one."""
        ros = component.ros
        version = ros.version if ros is not None else 2
        given = ros.python if ros is not None else ""
        if given:
            hint = f"set ros: python: to an interpreter with ROS {version} and the cast package (docs/ros.md)"
            return str(resolve_executable(component, given, env, hint))
        if version == 2:
            return env.get("CAST_ROS2_PYTHON") or sys.executable
        chosen = env.get("CAST_ROS1_PYTHON") or "/usr/bin/python3"
        if not Path(chosen).is_file():
            raise LaunchError(f"component '{component.id}': no ROS 1 interpreter at {chosen}: install ROS 1 (Debian: "
                              "python3-rospy) or set ros: python: / $CAST_ROS1_PYTHON (docs/ros.md)")
        return chosen

    def command(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> list[str]:
        """The bridge's interpreter running the Python runner on the bridge of its ROS generation."""
        version = component.ros.version if component.ros is not None else 2
        bridge = "cast.bridges.ros.ros2:Ros2Bridge" if version == 2 else "cast.bridges.ros.ros1:Ros1Bridge"
        return [self.python(component, env), "-m", "cast.run", bridge]

    def environment(self, component: ComponentConfig, config: SystemConfig, env: Mapping[str, str]) -> dict[str, str]:
        """``CAST_ROS_BRIDGE``: the ``ros:`` section as JSON; output unbuffered."""
        ros = component.ros.to_dict() if component.ros is not None else {}
        return {"CAST_ROS_BRIDGE": json.dumps(ros), "PYTHONUNBUFFERED": "1"}

    def working_directory(self, component: ComponentConfig) -> Path | None:
        """The orchestrator's."""
        return None


LAUNCHERS: dict[str, Launcher] = {
    "python": PythonLauncher(), "cpp": CppLauncher(), "java": JavaLauncher(), "other": OtherLauncher(),
    "ros": RosLauncher(),
}


def register_launcher(language: str, launcher: Launcher) -> None:
    """Add or replace the launcher of a language."""
    LAUNCHERS[language] = launcher


def launcher_for(language: str) -> Launcher:
    """The launcher of a language; LaunchError if none is registered."""
    launcher = LAUNCHERS.get(language)
    if launcher is None:
        raise LaunchError(f"no launcher for language '{language}' (known: {', '.join(LAUNCHERS)})")
    return launcher
