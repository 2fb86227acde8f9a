"""Replaying a recording into a running system: its changes written again, with their timing.

Entry ids are kept: in CAST the writer chooses an entry's id (``Add`` names
the address), so a replay writes the ids the recording has, and a component
that looks for a known id finds it as it would on the robot. SAs are renamed by
``sa_map``. The replay keeps, per entry it wrote, the version its last write
returned and writes the next change of that entry against it
(``expected_version``): a live writer that changed or deleted the entry in
between is a *conflict*, reported, and the live state stands. A change of an
entry the replay never wrote (the recording started after its ADD, or
``start_s`` skipped it) is applied as it stands: an OVERWRITE adds a missing
entry, a DELETE of a missing one is nothing to do. ``cast.v1.Task`` changes
are not written: task entries belong to the live task managers.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial

from google.protobuf import descriptor_pb2

from cast.client.channel import Backoff
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import TASK_TYPE, Operation, WriteResult
from cast.errors import (
    AlreadyExistsError,
    CastError,
    ConsistencyError,
    InvalidArgumentError,
    LockedError,
    NotFoundError,
    UnavailableError,
)
from cast.recording.channels import Change
from cast.recording.reading import Recording

__all__ = ["ReplayOptions", "ReplayReport", "Replayer"]

_UNAVAILABLE_PATIENCE_S = 30.0


@dataclass(frozen=True)
class ReplayOptions:
    """How to replay: speed (None: as fast as possible), SA renaming, types, window, looping."""

    rate: float | None = 1.0
    sa_map: Mapping[str, str] = field(default_factory=dict)
    types: tuple[str, ...] = ()
    loop: bool = False
    start_s: float = 0.0
    end_s: float | None = None


@dataclass
class ReplayReport:
    """What a replay did: writes per operation, conflicts, changes not written and why, passes."""

    written: dict[str, int] = field(default_factory=lambda: {"add": 0, "overwrite": 0, "delete": 0})
    conflicts: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    skipped: dict[str, int] = field(default_factory=dict)
    passes: int = 0

    def skip(self, why: str) -> None:
        """Count a change that was not written, by reason."""
        self.skipped[why] = self.skipped.get(why, 0) + 1


class Replayer:
    """Writes a recording's changes into a live system through a privileged transport."""

    def __init__(self, recording: Recording, transport: GrpcTransport, options: ReplayOptions,
                 on_conflict: Callable[[str], None] = lambda line: None) -> None:
        self.recording = recording
        self.transport = transport
        self.options = options
        self.report = ReplayReport()
        self._on_conflict = on_conflict
        self._versions: dict[tuple[str, str], int] = {}  # live (SA, id) -> version of the replay's last write
        self.targets: dict[str, str] = {}

    # ---------------------------------------------------------------- checks

    def prepare(self) -> None:
        """Check everything that could make the replay fail part-way, and register the recorded schemas.

        InvalidArgumentError naming the problem (an SA that is not in the
        recording or not in the live system, a window outside the recording, an
        identity that may not write where the replay writes); the server's
        SchemaConflictError when a recorded type's schema differs from the live
        one. Nothing is written before this passes.
        """
        opts = self.options
        if opts.rate is not None and opts.rate <= 0:
            raise InvalidArgumentError(f"--rate {opts.rate}: give a speed factor above 0 (1.0: as recorded), or max")
        if opts.start_s < 0 or (opts.end_s is not None and opts.end_s <= opts.start_s):
            raise InvalidArgumentError(
                f"--from {opts.start_s} --to {opts.end_s}: give 0 <= FROM < TO, in seconds from the recording's start "
                f"(it lasts {self.duration_s:.3f} s)")
        if opts.start_s > self.duration_s:
            raise InvalidArgumentError(f"--from {opts.start_s}: the recording lasts {self.duration_s:.3f} s from its "
                                       "first change to its last; give a start within it")
        recorded_types = sorted({t for _, t in self.recording.value_channels()})
        unknown = [t for t in opts.types if t not in recorded_types]
        if unknown:
            raise InvalidArgumentError(f"--type {unknown[0]}: the recording has no values of that type (it holds: "
                                       f"{', '.join(recorded_types) or 'none'})")
        recorded = self.recording.subarchitectures
        live = self.transport.subarchitectures()
        for sa, target in opts.sa_map.items():
            if sa not in recorded:
                raise InvalidArgumentError(f"--sa-map {sa}={target}: the recording has no subarchitecture '{sa}' "
                                           f"(it holds: {', '.join(recorded) or 'none'})")
            if target not in live:
                raise InvalidArgumentError(f"--sa-map {sa}={target}: the live system has no subarchitecture "
                                           f"'{target}' (known: {', '.join(live)})")
        # Task entries are not replayed (the live task managers own them): their SAs need no live target.
        channels = {key: c for key, c in self.recording.value_channels().items()
                    if self._wanted(key[1]) and key[1] != TASK_TYPE}
        for sa in dict.fromkeys(sa for sa, _ in channels):
            target = opts.sa_map.get(sa, sa)
            if target not in live:
                raise InvalidArgumentError(
                    f"the recording's subarchitecture '{sa}' is not in the live system (known: {', '.join(live)}): "
                    f"map it with --sa-map {sa}=LIVE_SA, or leave its types out with --type")
            self.targets[sa] = target
        self._check_identity(sorted(set(self.targets.values())))
        files: dict[str, descriptor_pb2.FileDescriptorProto] = {}
        for channel in channels.values():
            schema = self.recording.schema(channel)
            if schema is not None and schema.data:
                for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                    files.setdefault(fd.name, fd)
        if files:
            # One registration, all or nothing: a type whose live schema differs stops the replay here.
            self.transport.register_schemas(list(files.values()))

    def _check_identity(self, targets: list[str]) -> None:
        who = self.transport.identity
        others = [sa for sa in targets if sa != who.subarchitecture]
        if others and not who.privileged:
            raise InvalidArgumentError(
                f"the replay runs as component '{who.component_id}' (SA '{who.subarchitecture}'), which is not "
                f"privileged and so may not write {', '.join(repr(sa) for sa in others)}: give a privileged token "
                "(`cast token cast-replay --privileged`), or unset CAST_TOKEN so that one is made from the system's "
                "secret")

    def _wanted(self, type_name: str) -> bool:
        return not self.options.types or type_name in self.options.types

    @property
    def duration_s(self) -> float:
        """Seconds from the recording's first change to its last."""
        return max(0, self.recording.end_ns - self.recording.start_ns) / 1e9

    # ------------------------------------------------------------------- run

    def run(self, stop: threading.Event) -> ReplayReport:
        """Replay once, or until ``stop`` with ``loop``; the report."""
        while not stop.is_set():
            self._pass(stop)
            self.report.passes += 1
            if not self.options.loop or stop.is_set():
                break
            self._clear(stop)
        return self.report

    def _pass(self, stop: threading.Event) -> None:
        opts = self.options
        origin = self.recording.start_ns + int(opts.start_s * 1e9)
        end = None if opts.end_s is None else self.recording.start_ns + int(opts.end_s * 1e9)
        topics = [c.topic for (sa, t), c in self.recording.value_channels().items() if self._wanted(t)]
        began = time.monotonic()
        for recorded in self.recording.changes(topics):
            if stop.is_set():
                return
            change = recorded.change
            if change.time_ns < origin or (end is not None and change.time_ns > end):
                continue
            if not self._wanted(change.type):
                continue
            if change.type == TASK_TYPE:
                self.report.skip("task changes (cast.v1.Task entries belong to the live task managers)")
                continue
            if change.operation is not Operation.DELETE and recorded.value is None:
                self.report.skip("values the recorder did not get (the entry was ODR-locked)")
                continue
            if opts.rate is not None:
                due = began + (change.time_ns - origin) / 1e9 / opts.rate
                if stop.wait(max(0.0, due - time.monotonic())):
                    return
            self._apply(change, recorded.value or b"")

    def _clear(self, stop: threading.Event) -> None:
        """Before the next pass of a loop: delete what the last one left, so every pass starts alike."""
        for (sa, entry_id), version in list(self._versions.items()):
            if stop.is_set():
                return
            try:
                self._write(partial(self.transport.delete, sa, entry_id, version))
            except (ConsistencyError, LockedError) as err:
                self._conflict(f"DELETE {sa}/{entry_id} (end of pass {self.report.passes})", err)
            except NotFoundError:
                pass
        self._versions.clear()

    # ---------------------------------------------------------------- writes

    def _apply(self, change: Change, value: bytes) -> None:
        sa = self.targets.get(change.subarchitecture, self.options.sa_map.get(change.subarchitecture,
                                                                              change.subarchitecture))
        key = (sa, change.id)
        what = f"{change.operation.name} {sa}/{change.id} (recorded revision {change.revision} by {change.author})"
        known = self._versions.get(key)
        op = change.operation
        t = self.transport
        try:
            if op is Operation.ADD:
                result = self._write(lambda: t.add(sa, change.id, change.type, value), key)
            elif op is Operation.OVERWRITE and known is not None:
                result = self._write(lambda: t.overwrite(sa, change.id, change.type, value, known))
            elif op is Operation.OVERWRITE:
                result = self._upsert(sa, change, value)
            else:
                result = self._write(lambda: t.delete(sa, change.id, known))
        except AlreadyExistsError as err:
            self._conflict(what, err, "the id is taken in the live system")
            self._versions.pop(key, None)
            return
        except (ConsistencyError, LockedError) as err:
            self._conflict(what, err)
            self._refresh(key)
            return
        except NotFoundError as err:
            self._versions.pop(key, None)
            if op is Operation.DELETE and known is None:
                self.report.skip("deletes of entries the live system does not have")
            else:
                self._conflict(what, err, "deleted by a live writer")
            return
        except CastError as err:
            self.report.errors.append(f"{what}: {err.message}")
            self._on_conflict(f"error: {what}: {err.message}")
            return
        self.report.written[op.name.lower()] += 1
        if op is Operation.DELETE:
            self._versions.pop(key, None)
        else:
            self._versions[key] = result.version

    def _upsert(self, sa: str, change: Change, value: bytes) -> WriteResult:
        # The replay did not write this entry: the recording's value replaces whatever is there, or adds it.
        try:
            return self._write(lambda: self.transport.overwrite(sa, change.id, change.type, value, None))
        except NotFoundError:
            return self._write(lambda: self.transport.add(sa, change.id, change.type, value), (sa, change.id))

    def _write(self, call: Callable[[], WriteResult], added: tuple[str, str] | None = None) -> WriteResult:
        """One write; while the server is away it is tried again.

        A retried ADD (``added``: its SA and id) that finds its id taken was
        applied before the connection broke (docs/client-protocol.md,
        "Reconnection"): its entry is read back for the version.
        """
        backoff = Backoff()
        deadline = time.monotonic() + _UNAVAILABLE_PATIENCE_S
        retried = False
        while True:
            try:
                return call()
            except UnavailableError:
                if time.monotonic() > deadline:
                    raise
                retried = True
                time.sleep(backoff.next())
            except AlreadyExistsError:
                if not retried or added is None:
                    raise
                entry = self.transport.get(*added)
                return WriteResult(entry.revision, entry.version)

    def _refresh(self, key: tuple[str, str]) -> None:
        """After a conflict, the live version is the base for the entry's next recorded change."""
        try:
            self._versions[key] = self.transport.get(*key).version
        except CastError:
            self._versions.pop(key, None)

    def _conflict(self, what: str, err: CastError, why: str = "") -> None:
        line = f"conflict: {what}: {why + ': ' if why else ''}{err.message}; the live state stands"
        self.report.conflicts.append(line)
        self._on_conflict(line)
