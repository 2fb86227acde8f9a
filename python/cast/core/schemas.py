"""Entry schemas: protobuf descriptors that clients register for the types they write.

With a type's schema the server rejects values whose bytes do not parse as
that type, and tools render entries as JSON. Types without a schema pass
through unchecked: the server never needs to know a type to store it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message, message_factory
from google.protobuf.descriptor import Descriptor, FileDescriptor
from google.protobuf.message import DecodeError

from cast.errors import InvalidArgumentError, NotFoundError

__all__ = ["SchemaRegistry", "files_of"]


class SchemaRegistry:
    """A descriptor pool of registered entry types, safe to share between threads."""

    def __init__(self) -> None:
        self._mutex = threading.Lock()
        self._pool = descriptor_pool.DescriptorPool()
        self._files: dict[str, descriptor_pb2.FileDescriptorProto] = {}
        self._classes: dict[str, type[message.Message]] = {}
        # Told (name, serialised file) of every newly added file, under the registry's mutex, so a
        # journal stores schemas in registration order (cast.core.journal.Journal.append_schemas).
        self.on_added: Callable[[list[tuple[str, bytes]]], None] | None = None

    def register(self, files: Iterable[descriptor_pb2.FileDescriptorProto]) -> list[str]:
        """Add .proto file descriptors (with their dependencies, in any order); return the message types defined.

        A file already registered with the same content is skipped; one with
        different content is refused with INVALID_ARGUMENT, since entries
        already stored were validated against the old one.
        """
        pending = {f.name: f for f in files}
        if not pending:
            raise InvalidArgumentError("no file descriptors given: send the .proto files of your entry types")
        types: list[str] = []
        with self._mutex:
            for name, fd in pending.items():
                known = self._files.get(name)
                if known is not None and _canonical(known) != _canonical(fd):
                    raise InvalidArgumentError(
                        f"schema file '{name}' is already registered with different content: entry types "
                        "cannot change while the server runs; give the changed file a new name or package"
                    )
            added: set[str] = set()

            def add(name: str, trail: tuple[str, ...]) -> None:
                if name in self._files or name in added:
                    return
                if name in trail:
                    raise InvalidArgumentError(f"schema files import each other in a cycle: {' -> '.join(trail)}")
                fd = pending.get(name)
                if fd is None:
                    raise InvalidArgumentError(
                        f"schema file '{trail[-1]}' imports '{name}', which was not sent and is not registered: "
                        "send every dependency too"
                    )
                for dep in fd.dependency:
                    add(dep, (*trail, name))
                try:
                    self._pool.Add(fd)
                except (TypeError, ValueError) as exc:
                    raise InvalidArgumentError(f"schema file '{name}' is invalid: {exc}") from exc
                self._files[name] = fd
                added.add(name)

            for name in pending:
                add(name, ())
            if added and self.on_added is not None:
                self.on_added([(name, self._files[name].SerializeToString()) for name in sorted(added)])
            for name in pending:
                fd = self._files[name]
                prefix = f"{fd.package}." if fd.package else ""
                types.extend(_message_names(prefix, fd.message_type))
        return types

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

    def validate(self, type_name: str, data: bytes) -> None:
        """INVALID_ARGUMENT if ``data`` does not parse as ``type_name`` (unknown types pass)."""
        cls = self._message_class(type_name)
        if cls is None:
            return
        try:
            cls.FromString(data)
        except (DecodeError, RuntimeError) as exc:
            raise InvalidArgumentError(
                f"value does not parse as {type_name} ({exc}): the bytes were written with another type "
                "or are corrupt; check the Any's type_url"
            ) from exc

    def to_json(self, type_name: str, data: bytes) -> object:
        """The value as a JSON-ready object; NOT_FOUND if the type's schema is unknown."""
        cls = self._message_class(type_name)
        if cls is None:
            raise NotFoundError(f"no schema registered for type '{type_name}'")
        msg = cls.FromString(data)
        return json_format.MessageToDict(msg, preserving_proto_field_name=True, descriptor_pool=self._pool)

    def files_for(self, type_name: str) -> list[descriptor_pb2.FileDescriptorProto]:
        """The file defining ``type_name`` and its dependencies, dependencies first."""
        try:
            desc = self._pool.FindMessageTypeByName(type_name)
        except KeyError:
            raise NotFoundError(
                f"no schema registered for type '{type_name}': the writing component registers it on its first write"
            ) from None
        out: list[descriptor_pb2.FileDescriptorProto] = []
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


def files_of(descriptor: Descriptor | Any) -> list[descriptor_pb2.FileDescriptorProto]:
    """The .proto file defining a message class's descriptor and all it imports, dependencies first."""
    out: list[descriptor_pb2.FileDescriptorProto] = []
    seen: set[str] = set()

    def visit(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            visit(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        out.append(proto)

    visit(descriptor.file)
    return out


def _clear_json_names(messages: Iterable[descriptor_pb2.DescriptorProto]) -> None:
    for m in messages:
        for f in (*m.field, *m.extension):
            f.ClearField("json_name")
        _clear_json_names(m.nested_type)


def _canonical(fd: descriptor_pb2.FileDescriptorProto) -> bytes:
    """The parts of a file descriptor that define its types, for comparing registrations.

    Protobuf runtimes differ in what they fill in besides the types: some set
    every field's ``json_name``, some leave it to be derived, and source info is
    optional. Two registrations of one file from different languages must
    compare equal, so those are left out.
    """
    copy = descriptor_pb2.FileDescriptorProto()
    copy.CopyFrom(fd)
    copy.ClearField("source_code_info")
    for f in copy.extension:
        f.ClearField("json_name")
    _clear_json_names(copy.message_type)
    return copy.SerializeToString(deterministic=True)
