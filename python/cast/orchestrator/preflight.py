"""The preflight: checks beyond the file itself, whether the classes import and the executables exist.

Used by ``cast check`` (a missing C++ or Java build is a warning there: the
file is fine, it just cannot run yet) and by ``cast run`` (where it is an
error, since the component could not be started). It lives here, not in
``cast.config``, because it asks the launchers and the Python runner: the
configuration package depends on nothing above it (a test checks that).
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from cast.client.runner import load_component_class
from cast.config.model import SystemConfig
from cast.config.problems import Problems
from cast.config.syspath import extended_sys_path
from cast.errors import CastError
from cast.orchestrator.launchers import launcher_for

__all__ = ["preflight"]


def preflight(
    config: SystemConfig, problems: Problems, builds_required: bool = False, env: Mapping[str, str] | None = None
) -> None:
    """Add a problem for each component that cannot be loaded or launched (an error if ``builds_required``)."""
    env = dict(os.environ if env is None else env)
    with extended_sys_path(config.python_path):
        for comp in config.components:
            where = f"components.{comp.id}"
            if comp.remote and comp.launched:
                continue  # checked on its host, by its agent: `cast check --probe`, and Launch itself
            if comp.language == "python":
                try:
                    cls = load_component_class(comp.cls)
                except CastError as exc:
                    problems.error(comp.at("class"), f"{where}.class", exc.message)
                    continue
                if getattr(cls, "kind", comp.kind) != comp.kind:
                    problems.error(
                        comp.at("kind"), f"{where}.kind",
                        f"'{comp.cls}' is a {cls.kind} component but the configuration says kind: {comp.kind}",
                    )
            if comp.manual or comp.in_process:
                continue
            try:
                launcher_for(comp.language).command(comp, config, env)
            except CastError as exc:
                key = {"cpp": "run", "other": "run", "ros": "ros"}.get(comp.language, "class")
                message = exc.message.removeprefix(f"component '{comp.id}': ")
                if builds_required:
                    problems.error(comp.at(key), f"{where}.{key}", message)
                else:
                    problems.warn(comp.at(key), f"{where}.{key}", message)
