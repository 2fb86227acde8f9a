"""The build hook of cast-grpc: the wire API's Python code goes into every sdist and wheel.

Everything else about the package is in pyproject.toml. The generated ``cast.v1`` modules are
never committed (``make proto`` makes them in a checkout), so the build makes them itself with
grpcio-tools' protoc (a build requirement) from ``proto/cast/v1``:

- ``build_py`` (wheels): into the build directory, after the package's own files are copied,
  with the repository's ``VERSION`` as ``cast/VERSION`` (what ``cast.version`` reads at run time);
- ``sdist``: into the sdist's tree, beside the ``proto/`` files that MANIFEST.in adds, so an
  sdist holds the code and can rebuild it.

An editable install (``make setup``: ``pip install -e .``) generates nothing: it imports the
checkout's ``python/cast/v1``, which ``make proto`` keeps current.

With ``CAST_MYPYC=1`` a wheel's build also compiles the modules in ``MYPYC_MODULES`` with mypyc
and builds the Python client's C decoder of EVENTS frames (``cast.client._events_native``)
(``make mypyc``; docs/decisions.md, "The compiled build"); any other build, and every editable one,
is pure Python.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "build_support"))
from cast_protos import generate  # noqa: E402


class BuildPyWithProtos(build_py):
    """``build_py`` that also generates ``cast/v1`` into the build directory."""

    def run(self) -> None:
        """Copy the package, then generate the wire API's code next to it (not for editable installs)."""
        super().run()
        if not self.editable_mode:
            generate(HERE / "proto", Path(self.build_lib), "the cast-grpc build (setup.py)")
            (Path(self.build_lib) / "cast" / "VERSION").write_text((HERE / "VERSION").read_text())


class SdistWithProtos(sdist):
    """``sdist`` whose tree holds the generated ``python/cast/v1`` too."""

    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        """Lay out the sdist's files, then generate the code into it from its own ``proto/``."""
        super().make_release_tree(base_dir, files)
        generate(Path(base_dir) / "proto", Path(base_dir) / "python", "the cast-grpc build (setup.py)")


# mypyc-compiled hot modules: only when CAST_MYPYC=1 (make bench's wheel, release wheels); a plain
# `pip install .` / `pip install -e .` (make setup) stays pure Python, so an edited .py is what runs.
MYPYC_MODULES = [
    *(f"python/cast/core/{m}.py" for m in (
        "access", "arena", "checks", "history", "host", "large_fields", "locks", "memory", "metrics",
        "planning", "records", "schemas", "shared", "system", "watch")),
    "python/cast/wire/values.py",
    "python/cast/wire/shared_memory.py",
    *(f"python/cast/server/{m}.py" for m in (
        "conversions", "event_encoding", "shared_socket", "socket_events", "socket_writes", "write_requests",
        "writes")),
]
ext_modules = []
if os.environ.get("CAST_MYPYC") == "1":
    if {"develop", "editable_wheel", "--inplace", "-i"} & set(sys.argv):
        sys.exit("CAST_MYPYC=1 builds wheels only: compiled modules in the tree would run instead of edited sources")
    from mypyc.build import mypycify

    # mypyc type-checks the package before build_py runs, so the wire API's code must be in the tree
    # first: a fresh checkout has none (make proto makes it; an sdist carries it).
    if not (HERE / "python" / "cast" / "v1" / "__init__.py").exists():
        generate(HERE / "proto", HERE / "python", "the compiled build (setup.py, CAST_MYPYC=1)")
    ext_modules = mypycify(
        MYPYC_MODULES,
        opt_level=os.environ.get("MYPYC_OPT_LEVEL", "3"),
        group_name="cast",
        target_dir="build/mypyc",
    )
    # The client's EVENTS frames decoded in C (docs/decisions.md, "EVENTS frames decoded in C"); without it
    # cast.client.conversions decodes them with protobuf.
    ext_modules.append(Extension(
        "cast.client._events_native", ["python/cast/client/events_native.c"], extra_compile_args=["-O2"],
    ))
    # Lent values claimed, read and given back in C (docs/decisions.md, "Claims, leases and fields in C"); without it
    # cast.client.shm_session and cast.client.views do it in Python.
    ext_modules.append(Extension(
        "cast.client._shared_native", ["python/cast/client/shared_native.c"], extra_compile_args=["-O2"],
    ))
    # A session's socket read, its frames cut and a watch's frame turned at once, in C (docs/decisions.md, "The
    # session's reads in C"); without it cast.client.shm_session and cast.client.watch_stream do it in Python.
    ext_modules.append(Extension(
        "cast.client._receive_native", ["python/cast/client/receive_native.c"], extra_compile_args=["-O2"],
    ))

setup(cmdclass={"build_py": BuildPyWithProtos, "sdist": SdistWithProtos}, ext_modules=ext_modules)
