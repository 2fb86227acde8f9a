"""Entry values as JSON, through the schemas their writers registered (``Directory.GetSchema``).

The view keeps its own :class:`cast.core.schemas.SchemaRegistry` (the one the
server uses, with the same rules for well-known files) and fills it as types
are met. A value it cannot render comes back as its type, its bytes in base64
and why, never as an error page: the page shows what it can.
"""

from __future__ import annotations

import base64
import re
import threading
from typing import Any

from google.protobuf import json_format

from cast.core.schemas import SchemaRegistry
from cast.errors import CastError
from cast.web.source import SystemSource

__all__ = ["ValueDecoder", "raw_value"]

_MAX_NESTED_TYPES = 16
_ANY_TYPE = re.compile(r"type_url:?\s*\S*/([\w.]+)")


def raw_value(type_name: str, data: bytes, why: str) -> dict[str, str]:
    """What is shown of a value that cannot be rendered: its type, its bytes (base64) and why."""
    return {"@type": type_name, "@bytes": base64.b64encode(data).decode("ascii"), "@error": why}


class ValueDecoder:
    """Renders values of a system's entries as JSON; thread-safe."""

    def __init__(self, source: SystemSource) -> None:
        self._source = source
        self._registry = SchemaRegistry()
        self._mutex = threading.Lock()

    def _load(self, sa: str, type_name: str) -> str | None:
        """Fetch and add a type's schema; None when done, else why it cannot be had."""
        try:
            files = self._source.schema(sa, type_name).files.file
        except CastError as exc:
            return "no schema registered for this type" if exc.code == "NOT_FOUND" else exc.message
        try:
            self._registry.register(files)
        except CastError as exc:
            return f"its schema cannot be loaded: {exc.message}"
        return None if self._registry.known(type_name) else "no schema registered for this type"

    def to_json(self, sa: str, type_name: str, data: bytes) -> Any:
        """The value as JSON; :func:`raw_value` when it cannot be rendered.

        Values inside ``Any`` fields (a task's data) are rendered through their
        own schemas, fetched as they are met.
        """
        with self._mutex:
            wanted = type_name
            for _ in range(_MAX_NESTED_TYPES):
                if not self._registry.known(wanted):
                    why = self._load(sa, wanted)
                    if why is not None:
                        return raw_value(type_name, data, why if wanted == type_name else f"{wanted}: {why}")
                try:
                    return self._registry.to_json(type_name, data)
                except CastError as exc:
                    return raw_value(type_name, data, exc.message)
                except (TypeError, KeyError, json_format.Error) as exc:
                    inner = _ANY_TYPE.search(str(exc))
                    if inner is None or inner.group(1) == wanted:
                        return raw_value(type_name, data, f"cannot render it as JSON: {exc}")
                    wanted = inner.group(1)  # an Any inside names a type not loaded yet
            return raw_value(type_name, data, f"nested types more than {_MAX_NESTED_TYPES} deep")
