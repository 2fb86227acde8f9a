"""Entry schemas: protobuf descriptors that clients register for the types they write.

With a type's schema the server rejects values whose bytes do not parse as
that type, and tools render entries as JSON. Types without a schema pass
through unchecked: the server never needs to know a type to store it.

Rules (docs/client-protocol.md, "Schemas"):

- The server's own files are preloaded and belong to it: every well-known
  ``google/protobuf/*.proto`` of the protobuf runtime (:data:`WELL_KNOWN`)
  and the system's ``cast/v1/*.proto``. A client's copy of one of them is
  accepted and ignored: never stored, never compared (runtimes ship them with
  and without options); ``GetSchema`` serves the server's copy.
- Any other file is stored as first registered. A later registration of the
  same file name is accepted when it defines the same types (compared by
  meaning: :mod:`cast.core.schema_compare`), whatever its options, json
  names, source info or comments; one that defines them differently (a new
  field included: entries already stored were checked against the first) is
  refused with FAILED_PRECONDITION naming the first difference, and nothing
  changes. A registration is all or nothing.
- Stored files read back from a journal go through the same rules; a stored
  copy of a preloaded file (older servers stored them) is dropped.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from google.protobuf import (
    any_pb2,
    api_pb2,
    descriptor_pb2,
    descriptor_pool,
    duration_pb2,
    empty_pb2,
    field_mask_pb2,
    json_format,
    message,
    message_factory,
    source_context_pb2,
    struct_pb2,
    timestamp_pb2,
    type_pb2,
    wrappers_pb2,
)
from google.protobuf.descriptor import Descriptor, FileDescriptor
from google.protobuf.message import DecodeError

from cast.core.large_fields import bytes_fields, without_large_bytes
from cast.core.schema_compare import first_difference
from cast.errors import InvalidArgumentError, NotFoundError, SchemaConflictError

__all__ = ["WELL_KNOWN", "SchemaRegistry", "files_of", "files_of_many"]

log = logging.getLogger("cast.schemas")

WELL_KNOWN: tuple[FileDescriptor, ...] = tuple(
    module.DESCRIPTOR
    for module in (
        any_pb2, api_pb2, descriptor_pb2, duration_pb2, empty_pb2, field_mask_pb2, source_context_pb2, struct_pb2,
        timestamp_pb2, type_pb2, wrappers_pb2,
    )
)
"""The well-known files every server preloads (``google/protobuf/*.proto`` of the runtime)."""

FileProto = descriptor_pb2.FileDescriptorProto


class SchemaRegistry:
    """A descriptor pool of registered entry types, safe to share between threads."""

    def __init__(self, own: Iterable[FileDescriptor] = ()) -> None:
        self._mutex = threading.Lock()
        self._pool = descriptor_pool.DescriptorPool()
        self._files: dict[str, FileProto] = {}
        self._own: set[str] = set()  # the server's files: client copies are ignored
        self._classes: dict[str, type[message.Message]] = {}
        self._bytes_fields: dict[str, frozenset[int]] = {}  # per type: its top-level bytes fields (validate)
        # Told (name, serialised file) of every newly added file, under the registry's mutex, so a
        # journal stores schemas in registration order (cast.core.journal.Journal.append_schemas).
        self.on_added: Callable[[list[tuple[str, bytes]]], None] | None = None
        with self._mutex:
            self._add_ordered(files_of_many((*WELL_KNOWN, *own)), own=True)

    @property
    def pool(self) -> descriptor_pool.DescriptorPool:
        """The descriptor pool (server reflection resolves entry types through it)."""
        return self._pool

    def is_own(self, name: str) -> bool:
        """Whether a file is one the server preloads (well-known, or the system's)."""
        return name in self._own

    def register(self, files: Iterable[FileProto]) -> list[str]:
        """Add .proto file descriptors (with their dependencies, in any order); return the message types defined.

        Client copies of the server's own files are ignored; see the module
        docstring for the rest. All or nothing: a refusal changes nothing.
        """
        given = list(files)
        if not given:
            raise InvalidArgumentError("no file descriptors given: send the .proto files of your entry types")
        with self._mutex:
            added = self._register_locked(given)
            if added and self.on_added is not None:
                self.on_added([(fd.name, fd.SerializeToString()) for fd in added])
            types: list[str] = []
            for name in dict.fromkeys(fd.name for fd in given):
                fd = self._files[name]
                types.extend(_message_names(f"{fd.package}." if fd.package else "", fd.message_type))
        return types

    def restore(self, stored: Sequence[bytes]) -> list[str]:
        """Load files a journal stored (in their order) under today's rules; return the names dropped."""
        dropped: list[str] = []
        with self._mutex:
            for data in stored:
                fd = FileProto.FromString(data)
                if fd.name in self._own:
                    differs = first_difference(self._files[fd.name], fd)
                    if differs:
                        log.warning("stored schema file '%s' differs from the server's own copy (%s): dropped",
                                    fd.name, differs)
                    dropped.append(fd.name)
                    continue
                try:
                    self._register_locked([fd], restoring=True)
                except (InvalidArgumentError, SchemaConflictError) as exc:
                    log.warning("stored schema file '%s' cannot be loaded (%s): dropped", fd.name, exc.message)
                    dropped.append(fd.name)
        return dropped

    def _register_locked(self, given: list[FileProto], restoring: bool = False) -> list[FileProto]:
        pending: dict[str, FileProto] = {}
        for fd in given:
            if fd.name in self._own:
                continue  # the server's copy rules; the client's is not even compared
            known = self._files.get(fd.name) or pending.get(fd.name)
            if known is not None:
                differs = first_difference(known, fd)
                if differs:
                    raise SchemaConflictError(
                        f"schema file '{fd.name}' is already registered with other types: {differs}; entries were "
                        "checked against the registered definition, so it cannot change: give the changed file a "
                        "new name or package"
                    )
                continue
            pending[fd.name] = fd
        ordered = self._in_dependency_order(pending)
        if not ordered:
            return []
        self._trial(ordered)
        self._add_ordered(ordered, own=False)
        return [] if restoring else ordered

    def _in_dependency_order(self, pending: dict[str, FileProto]) -> list[FileProto]:
        ordered: list[FileProto] = []
        placed: set[str] = set()

        def place(name: str, trail: tuple[str, ...]) -> None:
            if name in self._files or name in placed:
                return
            if name in trail:
                raise InvalidArgumentError(f"schema files import each other in a cycle: {' -> '.join((*trail, name))}")
            fd = pending.get(name)
            if fd is None:
                raise InvalidArgumentError(
                    f"schema file '{trail[-1]}' imports '{name}', which was not sent and is not registered: "
                    "send every dependency too"
                )
            for dep in fd.dependency:
                place(dep, (*trail, name))
            placed.add(name)
            ordered.append(fd)

        for name in pending:
            place(name, ())
        return ordered

    def _trial(self, ordered: list[FileProto]) -> None:
        """Add the files to a scratch pool first, so that an invalid one changes nothing."""
        scratch = descriptor_pool.DescriptorPool()
        needed: list[FileProto] = []
        seen: set[str] = set()

        def visit(name: str) -> None:
            if name in seen or name not in self._files:
                return
            seen.add(name)
            for dep in self._files[name].dependency:
                visit(dep)
            needed.append(self._files[name])

        for fd in ordered:
            for dep in fd.dependency:
                visit(dep)
            prefix = f"{fd.package}." if fd.package else ""
            for name in (*_message_names(prefix, fd.message_type), *(prefix + e.name for e in fd.enum_type)):
                try:
                    owner = self._pool.FindFileContainingSymbol(name).name
                except KeyError:
                    continue
                raise InvalidArgumentError(
                    f"schema file '{fd.name}' defines {name}, which '{owner}' already defines: send the file that "
                    "defines it (protoc's, under its real name) or import it"
                )
        try:
            for fd in (*needed, *ordered):
                scratch.Add(fd)
            for fd in ordered:  # cross-file references resolve only when a file's types are built
                scratch.FindFileByName(fd.name)
        except (TypeError, ValueError, KeyError) as exc:
            raise InvalidArgumentError(f"schema files {[fd.name for fd in ordered]} are invalid: {exc}") from exc

    def _add_ordered(self, ordered: Iterable[FileProto], own: bool) -> None:
        for fd in ordered:
            if fd.name in self._files:
                continue
            self._pool.Add(fd)
            self._files[fd.name] = fd
            if own:
                self._own.add(fd.name)

    def known_file(self, name: str) -> bool:
        """Whether a file of that name is registered (or the server's own)."""
        with self._mutex:
            return name in self._files

    def known(self, type_name: str) -> bool:
        """Whether the schema of a type is registered."""
        try:
            self._pool.FindMessageTypeByName(type_name)
        except KeyError:
            return False
        return True

    def _message_class(self, type_name: str) -> type[message.Message] | None:
        cls = self._classes.get(type_name)
        if cls is None:
            try:
                desc = self._pool.FindMessageTypeByName(type_name)
            except KeyError:
                return None
            cls = message_factory.GetMessageClass(desc)
            self._classes[type_name] = cls
        return cls

    def validate(self, type_name: str, data: bytes | memoryview) -> None:
        """INVALID_ARGUMENT if ``data`` does not parse as ``type_name`` (unknown types pass).

        Large ``bytes`` fields are left out of the parse (:mod:`cast.core.large_fields`): they
        cannot fail it, and copying them is most of what it would cost.
        """
        cls = self._message_class(type_name)
        if cls is None:
            return
        numbers = self._bytes_fields.get(type_name)
        if numbers is None:
            numbers = self._bytes_fields[type_name] = bytes_fields(self._pool.FindMessageTypeByName(type_name))
        lighter = without_large_bytes(data, numbers)
        try:
            # upb parses any buffer: a view of shared memory too
            cls.FromString(data if lighter is None else lighter)  # type: ignore[arg-type]
        except (DecodeError, RuntimeError) as exc:
            raise InvalidArgumentError(
                f"value does not parse as {type_name} ({exc}): the bytes were written with another type "
                "or are corrupt; check the Any's type_url"
            ) from exc

    def decode(self, type_name: str, data: bytes) -> message.Message:
        """The value as a message of the registered type; NOT_FOUND if unknown, INVALID_ARGUMENT if corrupt."""
        cls = self._message_class(type_name)
        if cls is None:
            raise NotFoundError(f"no schema registered for type '{type_name}'")
        try:
            return cls.FromString(data)
        except (DecodeError, RuntimeError) as exc:
            raise InvalidArgumentError(f"value does not parse as {type_name} ({exc})") from exc

    def to_json(self, type_name: str, data: bytes) -> object:
        """The value as a JSON-ready object; NOT_FOUND if the type's schema is unknown."""
        msg = self.decode(type_name, data)
        return json_format.MessageToDict(msg, preserving_proto_field_name=True, descriptor_pool=self._pool)

    def files_for(self, type_name: str) -> list[FileProto]:
        """The file defining ``type_name`` and its dependencies, dependencies first."""
        try:
            desc = self._pool.FindMessageTypeByName(type_name)
        except KeyError:
            raise NotFoundError(
                f"no schema registered for type '{type_name}': the writing component registers it on its first write"
            ) from None
        out: list[FileProto] = []
        seen: set[str] = set()

        def visit(name: str) -> None:
            if name in seen:
                return
            seen.add(name)
            fd = self._files[name]
            for dep in fd.dependency:
                visit(dep)
            out.append(fd)

        visit(desc.file.name)
        return out

    def types(self) -> list[str]:
        """Every registered message type."""
        with self._mutex:
            files = list(self._files.values())
        names: list[str] = []
        for fd in files:
            names.extend(_message_names(f"{fd.package}." if fd.package else "", fd.message_type))
        return sorted(names)


def _message_names(prefix: str, messages: Iterable[descriptor_pb2.DescriptorProto]) -> list[str]:
    out = []
    for m in messages:
        full = prefix + m.name
        out.append(full)
        out.extend(_message_names(full + ".", m.nested_type))
    return out


def files_of(descriptor: Descriptor | Any) -> list[FileProto]:
    """The .proto file defining a message class's descriptor and all it imports, dependencies first."""
    return files_of_many([descriptor.file])


def files_of_many(roots: Iterable[FileDescriptor]) -> list[FileProto]:
    """The given .proto files and all they import, dependencies first, each once."""
    out: list[FileProto] = []
    seen: set[str] = set()

    def visit(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            visit(dep)
        proto = FileProto()
        fd.CopyToProto(proto)
        out.append(proto)

    for root in roots:
        visit(root)
    return out
