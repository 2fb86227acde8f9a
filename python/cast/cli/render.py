"""Output of the inspection commands: rich tables for people, JSON for scripts, entries as JSON by schema."""

from __future__ import annotations

import base64
import json
import re
import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any

from google.protobuf import descriptor_pool, json_format, message_factory, timestamp_pb2
from google.protobuf.message import DecodeError
from rich.console import Console
from rich.table import Table

from cast.cli.connect import ServerStubs, SystemClient
from cast.errors import CastError
from cast.v1 import directory_pb2 as dir_pb2

__all__ = ["SchemaDecoder", "iso_time", "print_json", "print_table"]


def print_json(value: Any) -> None:
    """One JSON document on stdout."""
    sys.stdout.write(json.dumps(value, indent=2, sort_keys=False) + "\n")


def print_table(title: str, columns: Sequence[str], rows: Sequence[Sequence[Any]], numeric: Sequence[str] = ()) -> None:
    """A table on stdout (plain text when stdout is not a terminal)."""
    table = Table(title=title, title_justify="left")
    for col in columns:
        table.add_column(col, justify="right" if col in numeric else "left", overflow="fold")
    for row in rows:
        table.add_row(*("" if v is None else str(v) for v in row))
    Console(highlight=False, soft_wrap=False, width=None if sys.stdout.isatty() else 200).print(table)


def iso_time(ts: timestamp_pb2.Timestamp) -> str:
    """A timestamp as ISO 8601 in UTC (empty if unset)."""
    if not ts.seconds and not ts.nanos:
        return ""
    moment = datetime.fromtimestamp(ts.seconds + ts.nanos / 1e9, tz=UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


class SchemaDecoder:
    """Renders entry values as JSON through the schemas the writers registered (Directory.GetSchema)."""

    def __init__(self, client: SystemClient) -> None:
        self._client = client
        self._pool = descriptor_pool.DescriptorPool()
        self._files: set[str] = set()

    def _load(self, server: ServerStubs, type_name: str) -> bool:
        try:
            resp = self._client.call(server.directory.GetSchema, dir_pb2.GetSchemaRequest(type=type_name))
        except CastError:
            return False
        for fd in resp.files.file:  # dependencies come first
            if fd.name not in self._files:
                try:
                    self._pool.Add(fd)
                except (TypeError, ValueError):
                    pass  # already known under the same name (e.g. a well-known type)
                self._files.add(fd.name)
        try:
            self._pool.FindMessageTypeByName(type_name)
        except KeyError:
            return False
        return True

    def to_json(self, server: ServerStubs, type_name: str, data: bytes) -> Any:
        """The value as JSON; ``{"@type", "@bytes": base64, "@error": why}`` when it cannot be rendered.

        Values inside ``Any`` fields (a task's data) are rendered through their
        own registered schemas, fetched as they are met. Nothing here raises: a
        tool shows what it can and says why, never a traceback.
        """
        for _ in range(_MAX_NESTED_TYPES):
            try:
                desc = self._pool.FindMessageTypeByName(type_name)
            except KeyError:
                if not self._load(server, type_name):
                    return _raw(type_name, data, "no schema registered for this type")
                continue
            try:
                msg = message_factory.GetMessageClass(desc).FromString(data)
            except (DecodeError, RuntimeError) as exc:
                return _raw(type_name, data, f"the bytes do not parse as {type_name}: {exc}")
            try:
                return json_format.MessageToDict(msg, preserving_proto_field_name=True, descriptor_pool=self._pool)
            except (TypeError, KeyError, json_format.Error) as exc:
                # An Any inside names a type whose schema is not loaded yet: fetch it and try again.
                inner = _ANY_TYPE.search(str(exc))
                if inner is None or not self._load(server, inner.group(1)):
                    return _raw(type_name, data, f"cannot render it as JSON: {exc}")
        return _raw(type_name, data, f"nested types more than {_MAX_NESTED_TYPES} deep")


_MAX_NESTED_TYPES = 16
_ANY_TYPE = re.compile(r"type_url:?\s*\S*/([\w.]+)")


def _raw(type_name: str, data: bytes, why: str) -> dict[str, str]:
    return {"@type": type_name, "@bytes": base64.b64encode(data).decode("ascii"), "@error": why}
