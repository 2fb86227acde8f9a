"""The two versions an installation of CAST has: its library release and the wire API it speaks.

The release (``0.1.0``) is the repository's ``VERSION`` file, which the Python
package (setuptools reads it, and its build copies it in as ``cast/VERSION``), the
C++ library (CMake reads it) and the Java artifacts carry; the wire API (``cast.v1``) is the protobuf package of
``proto/cast/v1``, read here from the generated code so that it cannot
disagree with what is sent. docs/compatibility.md says which versions talk to
which.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from cast.v1 import directory_pb2

__all__ = ["DISTRIBUTION", "WIRE_API", "library_version", "version_line"]

DISTRIBUTION = "cast-grpc"
WIRE_API: str = directory_pb2.DESCRIPTOR.package


@cache
def library_version() -> str:
    """The installed package's release (its ``cast/VERSION``), or in a checkout the repository's ``VERSION``."""
    # A file beside this one rather than importlib.metadata: importing that costs every component
    # process ~0.05-0.08 s of CPU at start (with the email parser it loads), and a wheel's
    # cast/VERSION is the same file the metadata's version was read from (setup.py copies it).
    here = Path(__file__).resolve().parent
    for candidate in (here / "VERSION", here.parents[1] / "VERSION"):
        if candidate.is_file():
            return candidate.read_text().strip()
    return "unknown"


def version_line() -> str:
    """What ``cast --version`` prints."""
    return f"cast {library_version()} (wire API {WIRE_API})"
