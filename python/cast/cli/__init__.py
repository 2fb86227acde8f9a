"""The ``cast`` command line (``python -m cast.cli`` or the ``cast`` script)."""

from cast.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
