"""What a cluster engine cannot express: ``cast check --to ENGINE`` and ``cast export --to ENGINE``.

A configuration that ``cast run`` runs may still ask for something Kubernetes
or systemd cannot give it. Each such thing is refused here on the line that
asks for it, before anything is written, with what to change (docs/deploy.md,
"What an engine refuses"):

- **kubernetes**: the runtime images hold the checkout at ``/opt/cast``, so every
  path a container needs (``python_path``, a Java ``classpath:``, a C++ ``run:``
  path, the configuration and its includes) must be inside the checkout; a
  ``language: other`` component needs an image of its own; workload names are
  made from ids and must stay unique and short; a journal's directory becomes a
  volume, so it may hold nothing else; the TLS files become Secrets, so they
  must be readable now.
- **systemd**: the units run ``cast run`` (and ``cast agent``) in the checkout,
  so the configuration must be inside it.

The names of Kubernetes objects are made here too (:func:`component_object`,
:func:`server_object`), so that the check and the export agree on them.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path, PurePosixPath
from typing import Any

from cast.config.model import ComponentConfig, ServerConfig, SystemConfig
from cast.config.problems import Position, Problems
from cast.config.source import SourceTree, YList, YMap, load_tree
from cast.config.validate import build_config

__all__ = [
    "ENGINES",
    "IMAGE_ROOT",
    "NAME_LIMIT",
    "check_engine",
    "component_object",
    "in_image",
    "kube_name",
    "read_for_engine",
    "server_object",
]

ENGINES = ("kubernetes", "systemd")
IMAGE_ROOT = PurePosixPath("/opt/cast")  # where deploy/images/ put the checkout
# A StatefulSet's pods carry the label controller-revision-hash = NAME-<10 characters>, at most 63.
NAME_LIMIT = 52
_SYSTEM_DIRS = {Path(p) for p in ("/", "/bin", "/boot", "/dev", "/etc", "/lib", "/lib64", "/opt", "/proc", "/root",
                                  "/run", "/sbin", "/sys", "/usr", "/var")}
_JOURNAL_SUFFIXES = ("", "-wal", "-shm", "-journal")


def kube_name(text: str) -> str:
    """``text`` as a Kubernetes object name: lower case, anything but letters, digits and '-' made '-'."""
    return re.sub(r"-+", "-", re.sub(r"[^a-z0-9-]", "-", text.lower())).strip("-")


def component_object(comp: ComponentConfig) -> str:
    """The name of a component's Deployment (or Job)."""
    return kube_name(comp.id)


def server_object(server: ServerConfig) -> str:
    """The name of a server's Service and Deployment (or StatefulSet); also the host name components dial."""
    return f"server-{kube_name(server.name)}"


def in_image(path: Path, root: Path) -> PurePosixPath | None:
    """Where ``path`` of the checkout ``root`` is in the runtime images (None: outside the checkout)."""
    try:
        return IMAGE_ROOT / path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return None


def read_for_engine(
    path: str | os.PathLike[str],
    engine: str,
    root: Path,
    overrides: Mapping[str, str] | None = None,
    environ: Mapping[str, str] | None = None,
) -> tuple[SystemConfig | None, Problems]:
    """Read and validate a configuration, then check what ``engine`` cannot express (None if unreadable)."""
    tree = load_tree(path, overrides, environ)
    if not tree.readable:
        return None, tree.problems
    config = build_config(tree)
    if not tree.problems.errors:
        check_engine(tree, config, engine, root)
    return config, tree.problems


def check_engine(tree: SourceTree, config: SystemConfig, engine: str, root: Path) -> None:
    """Add a problem to ``tree.problems`` for everything in ``config`` that ``engine`` cannot express."""
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r} (known: {', '.join(ENGINES)})")
    _Checker(tree, config, root).check(engine)


class _Checker:
    def __init__(self, tree: SourceTree, config: SystemConfig, root: Path) -> None:
        self.root_map = tree.root
        self.p = tree.problems
        self.config = config
        self.root = root.resolve()

    def check(self, engine: str) -> None:
        files = self.config.files if engine == "kubernetes" else self.config.files[:1]
        for file in files:
            if in_image(file, self.root) is None:
                what = "the images hold" if engine == "kubernetes" else "the units run `cast run` in"
                self.p.error(Position(str(file)), "",
                             f"{file} is outside the checkout {self.root}, which {what}: move it into the "
                             "checkout, or run the command from the checkout's root")
        if engine == "kubernetes":
            self.names()
            self.images()
            self.paths()
            self.journals()
            self.tls_files()

    # ------------------------------------------------------------ kubernetes

    def names(self) -> None:
        """Workload names: unique after lower-casing, and short enough for a StatefulSet's labels."""
        taken: dict[str, str] = {}
        things: list[tuple[str, str, Position, str]] = [
            (server_object(s), f"server '{s.name}'", self._at("servers", s.name) or Position(self.config.source),
             f"servers.{s.name}") for s in self.config.servers
        ]
        things += [(component_object(c), f"component '{c.id}'", c.position, f"components.{c.id}")
                   for c in self.config.components if c.launched]
        for name, what, pos, key in things:
            if not name or len(name) > NAME_LIMIT:
                self.p.error(pos, key, f"{what} becomes the Kubernetes name '{name}' ({len(name)} characters), "
                                       f"but a workload's name has 1 to {NAME_LIMIT}: give it a shorter name of "
                                       "letters and digits")
            elif name in taken:
                self.p.error(pos, key, f"{what} becomes the Kubernetes name '{name}', which {taken[name]} has "
                                       "already (names are lower-cased, and '_' and '.' become '-'): rename one")
            else:
                taken[name] = f"{what} (line {pos.line})" if pos.line else what

    def images(self) -> None:
        for comp in self.config.components:
            if comp.launched and not self.config.images.for_component(comp):
                self.p.error(comp.at("language"), f"components.{comp.id}.language",
                             f"component '{comp.id}' (language other) runs its own program, which no runtime "
                             f"image has: give it an image with the program in it, images: {{components: "
                             f"{{{comp.id}: IMAGE}}}}")

    def paths(self) -> None:
        """Every path a runtime image must hold is in the checkout (/opt/cast in the image)."""
        comps = [c for c in self.config.components if not c.manual and c.id not in self.config.images.components]
        uses_python = any(c.language == "python" for c in comps) or any(
            ":" in sa.policy for sa in self.config.subarchitectures.values())
        if uses_python:
            raw = self.root_map.get("python_path")
            if isinstance(raw, YList):
                items = list(zip(raw, raw.item_pos, strict=True))
            else:
                items = [(raw, self.root_map.value_at("python_path"))] if raw is not None else []
            for (_, pos), path in zip(items, self.config.python_path, strict=False):
                self._inside(path, pos, "python_path", "a directory of python_path")
        for comp in comps:
            if not comp.launched:
                continue
            if comp.language == "java":
                for entry in comp.classpath:
                    self._inside(Path(entry), comp.at("classpath"), f"components.{comp.id}.classpath",
                                 f"on the class path of component '{comp.id}'")
            if comp.language == "cpp" and "/" in comp.run:
                self._inside(comp.base_dir / comp.run, comp.at("run"), f"components.{comp.id}.run",
                             f"the executable of component '{comp.id}'")

    def _inside(self, path: Path, pos: Position, key: str, what: str) -> None:
        if in_image(path, self.root) is None:
            self.p.error(pos, key, f"{path.resolve()} ({what}) is outside the checkout {self.root}, which the runtime "
                                   f"images hold at {IMAGE_ROOT}: move it into the checkout, or build an image of your "
                                   "own with it and name it in images:")

    def journals(self) -> None:
        """A journal's directory becomes the server's volume, which hides whatever else the directory holds."""
        needed = [*self.config.files, *self.config.python_path]
        for server in self.config.servers:
            if server.persistence is None:
                continue
            journal = server.persistence.path
            folder = journal.parent.resolve()
            pos = (self._at("servers", server.name, "persistence", "path", value=True)
                   or self._at("persistence", "path", value=True) or Position(self.config.source))
            key = f"servers.{server.name}.persistence.path" if "servers" in self.root_map else "persistence.path"
            if folder in _SYSTEM_DIRS or self.root.is_relative_to(folder):
                hidden = ["the checkout itself" if self.root.is_relative_to(folder) else f"{folder} of the image"]
            else:
                names = {journal.name + suffix for suffix in _JOURNAL_SUFFIXES}
                found = {p.resolve() for p in needed if p.resolve().is_relative_to(folder)}
                if folder.is_dir():
                    found |= {p for p in folder.iterdir() if p.name not in names}
                hidden = [str(p.relative_to(folder)) for p in sorted(found)]
            if hidden:
                shown = ", ".join(hidden[:3]) + (", ..." if len(hidden) > 3 else "")
                self.p.error(pos, key,
                             f"the journal directory {folder} of server '{server.name}' becomes its volume under "
                             f"Kubernetes, which would hide what else is there ({shown}): give the journal a "
                             "directory of its own, for example data/<server>/journal.sqlite")

    def tls_files(self) -> None:
        tls = self.config.tls
        if tls is None:
            return
        files = {"ca": tls.ca, "cert": tls.cert, "key": tls.key, "client_cert": tls.client_cert,
                 "client_key": tls.client_key}
        for key, path in files.items():
            if path is None:
                continue
            try:
                path.read_bytes()
            except OSError as exc:
                self.p.error(self._at("tls", key, value=True) or Position(self.config.source), f"tls.{key}",
                             f"cannot read {path} ({exc.strerror}): the export puts the TLS files into Secrets, "
                             "so they must be readable where it runs")

    # ------------------------------------------------------------------ tree

    def _at(self, *keys: str, value: bool = False) -> Position | None:
        """Where the key path ``keys`` is written (its value's position with ``value``), or None."""
        node: Any = self.root_map
        for key in keys[:-1]:
            node = node.get(key) if isinstance(node, YMap) else None
        if not isinstance(node, YMap) or keys[-1] not in node:
            return None
        return node.value_at(keys[-1]) if value else node.at(keys[-1])
