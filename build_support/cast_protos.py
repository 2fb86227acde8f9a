"""Generate the Python code of the wire API (proto/cast/v1) with grpcio-tools' protoc.

One generator for the two places the package's ``cast.v1`` code is made, so they cannot differ:

- ``make proto`` runs ``python build_support/cast_protos.py python`` on the checkout, for the
  editable install of ``.venv``;
- the setuptools build hook (``setup.py``) runs :func:`generate` into the wheel's build directory
  and into the sdist's tree, so both carry the code (it is never committed).

Output per ``.proto``: ``*_pb2.py``, ``*_pb2_grpc.py`` and their ``.pyi`` stubs (mypy-protobuf's
plugins), plus ``cast/v1/__init__.py``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["generate", "main"]

ROOT = Path(__file__).resolve().parent.parent


def _plugin(directory: Path, name: str, function: str) -> Path:
    """An executable running mypy-protobuf's ``function`` with this interpreter.

    Written rather than looked up on PATH: an isolated build environment's scripts are not always
    on it, and the interpreter running this is the one that has mypy-protobuf.
    """
    path = directory / name
    path.write_text(f'#!/bin/sh\nexec "{sys.executable}" -c "import sys; from mypy_protobuf.main import {function}; '
                    f'sys.exit({function}())" "$@"\n')
    path.chmod(0o755)
    return path


def generate(proto_root: Path, out_root: Path, made_by: str) -> list[Path]:
    """Write ``cast/v1`` below ``out_root`` from ``proto_root/cast/v1/*.proto``; the files written.

    ``made_by`` is said in the package's docstring (which command made it). The directory is
    replaced whole, so a file of a removed ``.proto`` does not linger (nor a hard link into a
    source tree get written through, when setuptools hard-links an sdist's files).
    """
    protos = sorted((proto_root / "cast" / "v1").glob("*.proto"))
    if not protos:
        raise SystemExit(f"cast_protos: no .proto files in {proto_root / 'cast' / 'v1'}: "
                         "run it from a checkout or an sdist of cast-grpc (they hold proto/)")
    target = out_root / "cast" / "v1"
    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    with tempfile.TemporaryDirectory(prefix="cast-protoc-") as tmp:
        mypy = _plugin(Path(tmp), "protoc-gen-mypy", "main")
        mypy_grpc = _plugin(Path(tmp), "protoc-gen-mypy_grpc", "grpc")
        command = [
            sys.executable, "-m", "grpc_tools.protoc", f"-I{proto_root}",
            f"--python_out={out_root}", f"--grpc_python_out={out_root}",
            f"--mypy_out=quiet:{out_root}", f"--mypy_grpc_out=quiet:{out_root}",
            f"--plugin=protoc-gen-mypy={mypy}", f"--plugin=protoc-gen-mypy_grpc={mypy_grpc}",
            *[str(p) for p in protos],
        ]
        done = subprocess.run(command, capture_output=True, text=True, env=os.environ.copy())
    if done.returncode != 0:
        raise SystemExit(f"cast_protos: protoc failed ({done.returncode}):\n{done.stdout}{done.stderr}\n"
                         "it needs grpcio-tools and mypy-protobuf (pyproject.toml's build requirements)")
    (target / "__init__.py").write_text(f'"""Generated from proto/cast/v1 by {made_by}; not committed."""\n')
    return sorted(target.iterdir())


def main(argv: list[str] | None = None) -> int:
    """``python build_support/cast_protos.py OUT_ROOT``: generate ``OUT_ROOT/cast/v1`` (make proto)."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python build_support/cast_protos.py OUT_ROOT   (make proto: OUT_ROOT is python)", file=sys.stderr)
        return 2
    written = generate(ROOT / "proto", Path(args[0]), "make proto")
    print(f"cast_protos: {len(written)} files in {Path(args[0]) / 'cast' / 'v1'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
