"""The two versions an installation of CAST has: its library release and the wire API it speaks.

The release (``0.1.0``) is the repository's ``VERSION`` file, which the Python
package (setuptools reads it), the C++ library (CMake reads it) and the Java
artifacts carry; the wire API (``cast.v1``) is the protobuf package of
``proto/cast/v1``, read here from the generated code so that it cannot
disagree with what is sent. docs/compatibility.md says which versions talk to
which.
"""

from __future__ import annotations

from functools import cache
from importlib import metadata
from pathlib import Path

from cast.v1 import directory_pb2

__all__ = ["DISTRIBUTION", "WIRE_API", "library_version", "version_line"]

DISTRIBUTION = "cast-grpc"
WIRE_API: str = directory_pb2.DESCRIPTOR.package


@cache
def library_version() -> str:
    """The installed package's release; in a checkout that is not installed, its ``VERSION`` file."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        tree = Path(__file__).resolve().parents[2] / "VERSION"
        return tree.read_text().strip() if tree.is_file() else "unknown"


def version_line() -> str:
    """What ``cast --version`` prints."""
    return f"cast {library_version()} (wire API {WIRE_API})"
