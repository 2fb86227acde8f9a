"""What a component's container runs: its image, its command line and its working directory.

The runtime images of ``deploy/images/`` hold the checkout at ``/opt/cast``
(:data:`cast.config.engines.IMAGE_ROOT`), built, so a component starts there
the way ``cast run``'s launchers start it on a host
(``cast.orchestrator.launchers``), with the checkout's paths moved under
``/opt/cast``:

- python: ``python -m cast.run module:Class``, ``python_path`` first on ``PYTHONPATH``;
- cpp: the ``run:`` executable; a bare name is found on the image's ``PATH``,
  which starts with ``/opt/cast/build/cpp/bin`` (``$CAST_CPP_BIN_DIR`` on a host);
- java: ``java -cp /opt/cast/java_client/target/cast-client-all.jar:<classpath>
  cast.client.Runner Class``;
- other: the ``run:`` words in the directory of the file that declares it, in
  the component's own image (``images.components``).

A path outside the checkout is kept as it is: ``cast check --to kubernetes``
refuses it for the runtime images, and an image of one's own may have it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cast.config.engines import IMAGE_ROOT, in_image
from cast.config.model import ComponentConfig, SystemConfig

__all__ = ["JAVA_CLIENT_JAR", "ContainerSpec", "component_container", "image_path"]

JAVA_CLIENT_JAR = IMAGE_ROOT / "java_client" / "target" / "cast-client-all.jar"
JAVA_RUNNER = "cast.client.Runner"


@dataclass(frozen=True)
class ContainerSpec:
    """The image, command line, working directory and extra environment of one component's container."""

    image: str
    argv: list[str]
    working_dir: str
    env: dict[str, str]


def image_path(path: Path, root: Path) -> str:
    """``path`` where the images have it: under /opt/cast if it is in the checkout, else as it is."""
    found = in_image(path, root)
    return str(found) if found is not None else str(path)


def component_container(comp: ComponentConfig, config: SystemConfig, root: Path) -> ContainerSpec:
    """How ``comp`` runs in its image."""
    image = config.images.for_component(comp)
    workdir = str(IMAGE_ROOT)
    env: dict[str, str] = {}
    if comp.language == "python":
        argv = ["python", "-m", "cast.run", comp.cls]
        if config.python_path:
            env["PYTHONPATH"] = ":".join(image_path(p, root) for p in config.python_path)
        env["PYTHONUNBUFFERED"] = "1"  # lines reach kubectl logs as printed
    elif comp.language == "cpp":
        argv = [_program(comp, comp.run, root)]
    elif comp.language == "java":
        classpath = [str(JAVA_CLIENT_JAR), *(image_path(Path(e), root) for e in comp.classpath)]
        argv = ["java", "-cp", ":".join(classpath), JAVA_RUNNER, comp.cls]
    else:
        program, *arguments = comp.command or [""]
        argv = [_program(comp, program, root), *arguments]
        workdir = image_path(comp.base_dir, root)
    return ContainerSpec(image, argv, workdir, env)


def _program(comp: ComponentConfig, name: str, root: Path) -> str:
    """A ``run:`` program: a bare name stays bare (the image's PATH finds it), a path moves with the checkout."""
    if "/" not in name:
        return name
    return image_path(comp.base_dir / name, root)
