"""Writing an export's directory: only into an empty one or one an earlier export wrote, and nothing stale.

An export lists what it wrote in ``DIR/.cast-export`` (JSON). Exporting again
into that directory first removes the files of the list, so a component taken
out of the configuration does not leave its manifest behind; a directory with
other files and no list is refused, so that an export never overwrites files
it did not write. Files holding a secret are written with mode 0600.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from cast.errors import InvalidArgumentError

__all__ = ["MARKER", "OutputFile", "write_output", "yaml_documents"]

MARKER = ".cast-export"


@dataclass
class OutputFile:
    """One file of an export: its path relative to the directory, its text, whether it holds a secret."""

    name: str
    text: str
    private: bool = False
    executable: bool = False
    notes: list[str] = field(default_factory=list)


class _Dumper(yaml.SafeDumper):
    """Writes a value shared by two places twice, rather than as an anchor and an alias (``&id001``)."""

    def ignore_aliases(self, data: Any) -> bool:
        return True


def yaml_documents(header: str, documents: Iterable[dict[str, Any]]) -> str:
    """YAML documents separated by ``---``, after a comment ``header``."""
    comment = "".join(f"# {line}\n" for line in header.splitlines())
    body = "---\n".join(yaml.dump(doc, Dumper=_Dumper, sort_keys=False, default_flow_style=False, width=120)
                        for doc in documents)
    return comment + body


def write_output(out_dir: Path, files: list[OutputFile], engine: str, source: str) -> None:
    """Write ``files`` into ``out_dir`` (made if missing), after removing an earlier export's files there."""
    out_dir.mkdir(parents=True, exist_ok=True)
    _clear(out_dir)
    for item in files:
        path = out_dir / item.name
        path.parent.mkdir(parents=True, exist_ok=True)
        mode = 0o600 if item.private else (0o755 if item.executable else 0o644)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "w") as f:
            f.write(item.text)
        os.chmod(path, mode)  # also when the file was there already
    marker = {"engine": engine, "config": source, "files": [item.name for item in files]}
    (out_dir / MARKER).write_text(json.dumps(marker, indent=1) + "\n")


def _clear(out_dir: Path) -> None:
    """Remove an earlier export's files; refuse a directory holding anything else."""
    marker = out_dir / MARKER
    if not marker.exists():
        found = sorted(p.name for p in out_dir.iterdir())
        if found:
            shown = ", ".join(found[:4]) + (", ..." if len(found) > 4 else "")
            raise InvalidArgumentError(f"{out_dir} is not empty ({shown}) and holds no earlier export ({MARKER}): "
                                       "give a new or empty directory, so that nothing of yours is overwritten")
        return
    try:
        listed = json.loads(marker.read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InvalidArgumentError(f"{marker} cannot be read ({exc}): remove {out_dir} or give another "
                                   "directory") from None
    for name in listed:
        path = (out_dir / str(name)).resolve()
        if path.is_relative_to(out_dir.resolve()) and path.is_file():
            path.unlink()
    for sub in sorted((p for p in out_dir.rglob("*") if p.is_dir()), reverse=True):
        if not any(sub.iterdir()):
            sub.rmdir()
