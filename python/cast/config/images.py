"""The ``images:`` section: which container image runs what under ``cast export --to kubernetes``.

The schema pass has checked every image reference already (and removed the
wrong ones); what is left to say here ties the section to the rest of the
file: ``images.components`` names components of this system, and never one
that runs in process (it lives inside its server's container, so an image of
its own would be a container of its own that nothing starts). Both are
reported by every ``cast check``, not only for an export, since the file
itself is wrong.
"""

from __future__ import annotations

from cast.config.model import ImagesConfig, SystemConfig
from cast.config.problems import Problems, did_you_mean
from cast.config.schema import defaults
from cast.config.source import YMap

__all__ = ["build_images"]


def build_images(root: YMap, config: SystemConfig, problems: Problems) -> ImagesConfig:
    """The ``images:`` section of ``root`` (its defaults where not written); problems added to ``problems``."""
    raw = root.get("images")
    raw = raw if isinstance(raw, YMap) else YMap(root.pos)
    d = defaults("images")

    def text(key: str) -> str:
        value = raw.get(key)
        return str(d[key] if value is None else value)

    images = ImagesConfig(python=text("python"), cpp=text("cpp"), java=text("java"), pull_policy=text("pull_policy"))
    own = raw.get("components")
    for comp_id, image in (own or {}).items():
        assert isinstance(own, YMap)
        comp = config.component(comp_id)
        where = f"images.components.{comp_id}"
        if comp is None:
            known = [c.id for c in config.components]
            problems.error(own.at(comp_id), where,
                           f"no component '{comp_id}' in this system{did_you_mean(comp_id, known)}: an image of its "
                           "own is given to a component by its id")
        elif comp.in_process:
            server = config.server_of(comp.subarchitecture).name if config.servers else "its server"
            problems.error(own.at(comp_id), where,
                           f"component '{comp_id}' is in_process: it runs inside server '{server}', in that server's "
                           f"container (images.python), and cannot have a container of its own: remove "
                           f"images.components.{comp_id}, or 'in_process: true' (line {comp.at('in_process').line})")
        elif image is not None:
            images.components[comp_id] = str(image)
    return images
