"""A CAST system for one test: a real server on a free port, and what a test does with it.

:func:`start_system` serves a configuration (a YAML file, a dict, or just SA
names) in the test's process or as ``cast serve``; :func:`cast.testing.run_system`
runs a whole configuration, components and all, with ``cast run``. Either gives a
:class:`LocalSystem`, which mints tokens with the system's secret and hands
out what a test needs: components bound to the system (:meth:`LocalSystem.bind`),
components running their lifecycle (:meth:`LocalSystem.run`), the test acting
as another component (:meth:`LocalSystem.act_as`), collected change events
(:meth:`LocalSystem.collect_changes`), and assertions on entries. Its runtime
directory is a temporary one, removed when the system is closed, which also
stops every component it started and the server.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import yaml
from google.protobuf.message import Message

from cast.auth import TokenSigner
from cast.client.component import Component, UnmanagedComponent
from cast.client.filters import ChangeFilter, operation_filter
from cast.client.grpc_transport import GrpcTransport
from cast.client.types import Entry
from cast.config import SystemConfig, read_config
from cast.core.records import Identity
from cast.errors import InvalidArgumentError, NotFoundError
from cast.testing.actors import Actor, RunningComponent
from cast.testing.changes import ChangeCollector
from cast.testing.describe import describe_entry, describe_value
from cast.testing.servers import InProcessServer, ServeProcess, Server
from cast.testing.waiting import DEFAULT_TIMEOUT_S, wait_for

__all__ = ["DEFAULT_SUBARCHITECTURES", "LocalSystem", "start_system"]

C = TypeVar("C", bound=Component)
M = TypeVar("M", bound=Message)

DEFAULT_SUBARCHITECTURES = ("vision", "language")
"""The SAs of a system started without a configuration."""

OBSERVER = "cast-testing"
"""The id under which the kit itself reads (assert_entry, components); privileged, in the first SA."""

Config = str | os.PathLike[str] | Mapping[str, Any] | None
"""A configuration: a YAML file's path, the same as a dict, or None (a system of the SAs given)."""

Expected = Message | Callable[[Any], bool] | None
"""What an entry should hold: a value (compared field by field), a test of the value, or None (anything)."""


def _new_secret(directory: Path) -> tuple[bytes, Path]:
    """A fresh secret for the test, in a file only its owner reads (what ``cast serve --secret-file`` takes)."""
    secret = secrets.token_urlsafe(32).encode()
    path = directory / "secret"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(secret + b"\n")
    return secret, path


def _config_file(config: Config, subarchitectures: Sequence[str] | None, directory: Path) -> Path:
    """The configuration as a file: the one given, or a YAML file written into the system's directory."""
    if config is not None and subarchitectures is not None:
        raise InvalidArgumentError("give a configuration or subarchitectures, not both: the configuration names "
                                   "its own subarchitectures")
    if config is None:
        names = list(subarchitectures or DEFAULT_SUBARCHITECTURES)
        if not names:
            raise InvalidArgumentError("a system needs at least one subarchitecture")
        config = {"system": "test", "subarchitectures": {name: {} for name in names}}
    if isinstance(config, Mapping):
        path = directory / "system.yaml"
        path.write_text(yaml.safe_dump(dict(config), sort_keys=False))
        return path
    path = Path(config).resolve()
    if not path.is_file():
        raise NotFoundError(f"no configuration file {path}: give the path of a system's YAML file, or a dict")
    return path


def _load(path: Path, sets: Mapping[str, str], source: Config) -> SystemConfig:
    config, problems = read_config(path, sets)
    if config is None or problems.errors:
        shown = "the configuration given as a dict" if isinstance(source, Mapping) else str(path)
        raise InvalidArgumentError(f"{shown} has errors:\n" + "\n".join(str(p) for p in problems.errors))
    if config.tls is not None:
        raise InvalidArgumentError(f"{path} asks for TLS (tls:): start_system serves plaintext on 127.0.0.1; test "
                                   "a TLS configuration with run_system, which reaches it as `cast run` records")
    return config


class LocalSystem:
    """A system a test runs against; close it (or use it as a context manager) to stop everything.

    Made by :func:`start_system` or :func:`run_system`, not directly.
    """

    def __init__(
        self, server: Server, secret: bytes, name: str, subarchitectures: Sequence[str], directory: Path,
        own_directory: bool, runtime_dir: Path | None = None,
    ) -> None:
        self._server = server
        self._signer = TokenSigner(secret)
        self.name = name
        """The system's name (``system:`` of its configuration)."""
        self.subarchitectures = list(subarchitectures)
        """Its SAs, in the configuration's order."""
        self.directory = directory
        """The system's temporary directory (its configuration, secret and logs), removed on close."""
        self.runtime_dir = runtime_dir
        """With :func:`run_system`, the runtime directory `cast run` writes (inside :attr:`directory`)."""
        self._own_directory = own_directory
        self._components: list[Component] = []
        self._running: list[RunningComponent[Any]] = []
        self._collectors: list[ChangeCollector] = []
        self._observer: Actor | None = None
        self._closed = False
        self.exit_code: int | None = None
        """The server's (or `cast run`'s) exit status, once closed."""

    # ------------------------------------------------------------ who is who

    @property
    def endpoint(self) -> str:
        """The directory's ``host:port`` (on 127.0.0.1)."""
        return self._server.endpoint

    def token(self, component_id: str, subarchitecture: str, *, privileged: bool = False) -> str:
        """A token for a component of this system (what ``cast token`` would issue)."""
        return self._signer.issue(Identity(component_id, subarchitecture, privileged))

    def launch_environment(
        self, component_id: str, subarchitecture: str, *, args: Mapping[str, Any] | None = None,
        privileged: bool = False,
    ) -> dict[str, str]:
        """The launch contract of a component process started by the test (docs/design.md section 6).

        The ``CAST_*`` variables only: start the process with ``{**os.environ, **env}``.
        """
        return {
            "CAST_ENDPOINT": self.endpoint,
            "CAST_COMPONENT_ID": component_id,
            "CAST_SUBARCHITECTURE": subarchitecture,
            "CAST_TOKEN": self.token(component_id, subarchitecture, privileged=privileged),
            "CAST_ARGS": json.dumps(dict(args or {})),
        }

    def _transport(self, component_id: str, subarchitecture: str, privileged: bool) -> GrpcTransport:
        self._check_open()
        if subarchitecture not in self.subarchitectures:
            raise InvalidArgumentError(f"no subarchitecture '{subarchitecture}' in system '{self.name}' (it has "
                                       f"{', '.join(self.subarchitectures)})")
        identity = Identity(component_id, subarchitecture, privileged)
        return GrpcTransport(self.endpoint, self.token(component_id, subarchitecture, privileged=privileged),
                             identity)

    # ------------------------------------------------------------ components

    def act_as(self, component_id: str, subarchitecture: str, *, privileged: bool = False) -> Actor:
        """The test acting as component ``component_id`` of ``subarchitecture``: its writes, reads and tasks.

        Closed with the system (or by its ``close()``).
        """
        actor = Actor()
        actor._cast_bind(self._transport(component_id, subarchitecture, privileged))
        self._components.append(actor)
        return actor

    def bind(
        self, component: C | type[C], component_id: str, subarchitecture: str, *, privileged: bool = False,
    ) -> C:
        """A component (a class is instantiated) bound to the system, its hooks left to the test to call.

        For stepping a component: the test calls ``configure(args)``, ``start()``
        and its other methods itself, and acts in between. Closed with the system.
        """
        instance = component() if isinstance(component, type) else component
        instance._cast_bind(self._transport(component_id, subarchitecture, privileged))
        self._components.append(instance)
        return instance

    def run(
        self, component: C | type[C], component_id: str, subarchitecture: str, *,
        args: Mapping[str, Any] | None = None, privileged: bool = False, timeout: float = DEFAULT_TIMEOUT_S,
    ) -> RunningComponent[C]:
        """A component (a class is instantiated) running its lifecycle on a thread, as the runner runs it.

        ``configure(args)``, ``start()``, then ``run()``; returns once ``start()``
        returned, so its watches are registered. Stop it with
        :meth:`RunningComponent.stop` (and assert the exit code), or leave it to
        :meth:`close`. A hook that raised shows as exit code 1 and in the log.
        """
        instance = component() if isinstance(component, type) else component
        running = RunningComponent(instance, self._transport(component_id, subarchitecture, privileged),
                                   dict(args or {}))
        self._running.append(running)
        running.wait_started(timeout)
        return running

    # ------------------------------------------------------------ observing

    def _observe(self) -> Actor:
        if self._observer is None:
            self._observer = self.act_as(OBSERVER, self.subarchitectures[0], privileged=True)
        return self._observer

    def _directory_view(self) -> GrpcTransport:
        transport = self._observe()._transport
        assert isinstance(transport, GrpcTransport)
        return transport

    def collect_changes(self, *filters: ChangeFilter, subarchitecture: str | None = None) -> ChangeCollector:
        """Collect every change matching ``filters`` (default: every change of every SA, with its entry).

        The watch is registered before this returns. Local filters
        (``local_type_filter``, ``address_filter`` without an SA) mean
        ``subarchitecture`` (default: the first SA).
        """
        sa = subarchitecture or self.subarchitectures[0]
        watcher = UnmanagedComponent()
        watcher._cast_bind(self._transport(f"{OBSERVER}-changes-{len(self._collectors) + 1}", sa, True))
        collector = ChangeCollector(watcher)
        self._collectors.append(collector)
        watcher.on_change(list(filters) or [operation_filter(include_entry=True)], collector._collect)
        return collector

    def _describe_wm(self, subarchitecture: str) -> str:
        """The ids and types in an SA's WM, for a failure message (the listing `cast ls` shows)."""
        import grpc

        from cast.v1 import inspection_pb2, inspection_pb2_grpc

        try:
            with grpc.insecure_channel(self.endpoint) as channel:
                listing = inspection_pb2_grpc.InspectionStub(channel).ListEntries(
                    inspection_pb2.ListEntriesRequest(subarchitecture=subarchitecture),
                    metadata=(("authorization", f"Bearer {self.token(OBSERVER, subarchitecture)}"),), timeout=10)
        except grpc.RpcError as exc:
            return f"its entries could not be listed ({exc.code().name})"
        ids = [f"{e.address.id} ({e.type})" for e in listing.entries]
        if not ids:
            return "that WM is empty"
        return f"entries there: {', '.join(ids[:20])}{', ...' if len(ids) > 20 else ''}"

    def assert_entry(self, subarchitecture: str, entry_id: str, cls: type[M], expected: Expected = None) -> Entry[M]:
        """The entry, which must exist, be a ``cls`` and hold ``expected``; AssertionError saying what it holds.

        ``expected``: a value (equal field by field), a function of the value
        that returns whether it is right, or None (any value).
        """
        where = f"entry '{entry_id}' in subarchitecture '{subarchitecture}'"
        try:
            entry = self._observe().get_entry(entry_id, cls, subarchitecture=subarchitecture)
        except NotFoundError:
            raise AssertionError(f"no {where}; {self._describe_wm(subarchitecture)}") from None
        except InvalidArgumentError as exc:
            raise AssertionError(f"{where}: {exc}") from None
        if expected is None:
            return entry
        if isinstance(expected, Message):
            if entry.value != expected:
                raise AssertionError(f"{where} holds {describe_entry(entry)}, expected {describe_value(expected)}")
        elif not expected(entry.value):
            name = getattr(expected, "__name__", "<lambda>")
            test = "the test" if name == "<lambda>" else f"{name}()"
            raise AssertionError(f"{where} holds {describe_entry(entry)}, which {test} refused")
        return entry

    def wait_for_entry(
        self, subarchitecture: str, entry_id: str, cls: type[M], expected: Expected = None,
        timeout: float = DEFAULT_TIMEOUT_S,
    ) -> Entry[M]:
        """Wait until :meth:`assert_entry` holds; the entry. The failure says what the entry last held."""
        return wait_for(lambda: self.assert_entry(subarchitecture, entry_id, cls, expected), timeout,
                        f"entry '{entry_id}' in subarchitecture '{subarchitecture}'")

    def components(self) -> dict[str, Any]:
        """What the directory knows of each component, by id (``cast.v1`` ComponentInfo: ``state``, ``kind``, ...)."""
        return {c.id: c for c in self._directory_view().describe().components}

    def wait_for_component(self, component_id: str, state: str = "running", timeout: float = DEFAULT_TIMEOUT_S) -> Any:
        """Wait until the directory shows a component in ``state``; its ComponentInfo.

        ``state`` in the words of ``cast components``: expected, starting,
        started, running, stopping, disconnected. The failure says what the
        directory showed last.
        """
        from cast.v1 import directory_pb2

        wanted = directory_pb2.ComponentState.Value(f"COMPONENT_STATE_{state.upper()}")

        def reached() -> Any:
            info = self.components().get(component_id)
            shown = "not known" if info is None else \
                directory_pb2.ComponentState.Name(info.state).removeprefix("COMPONENT_STATE_").lower()
            assert info is not None and info.state == wanted, f"component '{component_id}' is {shown}"
            return info

        return wait_for(reached, timeout, f"component '{component_id}' to be {state}")

    # ------------------------------------------------------------ the server

    def output(self) -> str:
        """What the server (or `cast run`, with its components' lines) printed or logged so far."""
        return self._server.output()

    def kill(self) -> None:
        """Stop the server at once, as a crash would: clients see their connections break."""
        self._check_open()
        self._server.kill()

    def restart(self) -> None:
        """A new server with empty memories on the same address (the old one is killed first).

        Components reconnect by themselves; what the old server held is gone.
        """
        self._check_open()
        self._server.restart()

    def _check_open(self) -> None:
        if self._closed:
            raise InvalidArgumentError(f"system '{self.name}' is closed: start another one")

    def close(self) -> int:
        """Stop everything: running components (stop() once each), bound ones, the server; remove the directory.

        Returns the server's exit status (0 in process). Idempotent. Errors of
        a component's stop are in the log; its exit code is the test's to assert.
        """
        if self._closed:
            return self.exit_code or 0
        self._closed = True
        try:
            for running in reversed(self._running):
                with contextlib.suppress(AssertionError):
                    running.stop()
            for collector in self._collectors:
                collector.close()
            for component in reversed(self._components):
                component.request_stop()
                component._cast_close()
        finally:
            try:
                self.exit_code = self._stop_server()
            finally:
                if self._own_directory:
                    shutil.rmtree(self.directory, ignore_errors=True)
        return self.exit_code

    def _stop_server(self) -> int:
        return self._server.stop()

    def __enter__(self) -> LocalSystem:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None,
    ) -> None:
        self.close()


def _directory(directory: str | os.PathLike[str] | None) -> tuple[Path, bool]:
    if directory is not None:
        path = Path(directory)
        path.mkdir(parents=True, exist_ok=True)
        return path, False
    return Path(tempfile.mkdtemp(prefix="cast-testing-")), True


def start_system(
    config: Config = None, *, subarchitectures: Sequence[str] | None = None, process: bool = False,
    sets: Mapping[str, str] | None = None, directory: str | os.PathLike[str] | None = None,
) -> LocalSystem:
    """Serve a system for a test: a real server on a free port of 127.0.0.1, with a secret of its own.

    Args:
        config: a configuration's YAML file, the same as a dict, or None for a
            system of ``subarchitectures`` (default ``vision`` and ``language``)
            whose task managers adopt every task.
        subarchitectures: the SAs of a system without a configuration.
        process: serve with ``cast serve`` in a process of its own (as a
            deployment does) instead of on a thread of the test's process (the
            default: the same server code, started in a fraction of the time).
            Either way the configuration's in-process components are started.
        sets: values of the configuration's variables (``--set NAME=VALUE``).
        directory: where the system's files go (default: a temporary directory,
            removed when the system is closed).

    Returns:
        The running :class:`LocalSystem`; close it, or use it in a ``with`` block.

    """
    where, own = _directory(directory)
    try:
        path = _config_file(config, subarchitectures, where)
        loaded = _load(path, sets or {}, config)
        secret, secret_file = _new_secret(where)
        server: Server
        if process:
            server = ServeProcess(path, secret_file, where,
                                  [arg for name, value in (sets or {}).items() for arg in ("--set", f"{name}={value}")])
        else:
            server = InProcessServer(loaded, secret)
    except BaseException:
        if own:
            shutil.rmtree(where, ignore_errors=True)
        raise
    return LocalSystem(server, secret, loaded.name, list(loaded.subarchitectures), where, own)
