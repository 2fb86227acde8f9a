"""The component model (docs/design.md section 5): base classes and the WM vocabulary.

A component subclasses :class:`UnmanagedComponent` or :class:`ManagedComponent`
and overrides lifecycle hooks. Every working-memory call is addressed to the
component's own subarchitecture unless ``subarchitecture=`` names another.
Values are protobuf messages; a write serialises (so later changes to the
object do not reach the WM) and a read returns a fresh object, in process too.
"""

from __future__ import annotations

import itertools
import logging
import secrets
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any, TypeVar

from google.protobuf.message import Message

from cast.client.delivery import Delivery, LatestSlots, Priority, delivery_of, priority_of
from cast.client.dispatcher import Dispatcher
from cast.client.filters import ChangeFilter, type_name
from cast.client.loan import Loan, loan_header
from cast.client.transport import Transport
from cast.client.types import Entry, Task, WorkingMemoryAddress, WorkingMemoryChange, decode, entry_of
from cast.client.views import ValueView
from cast.core.records import BatchOp, ChangeEvent, Identity, LockMode, Operation, WriteResult
from cast.core.schemas import files_of
from cast.core.sessions import ComponentState
from cast.core.tasks import TaskOutcome, TaskRecord, TaskState
from cast.errors import CastError, InvalidArgumentError

__all__ = ["Component", "LockGuard", "ManagedComponent", "UnmanagedComponent", "WatchHandle"]

log = logging.getLogger("cast.component")

M = TypeVar("M", bound=Message)

class WatchHandle:
    """Returned by ``on_change``; ``cancel()`` stops the callback."""

    def __init__(self, component: Component, watch_id: int) -> None:
        self._component = component
        self.watch_id = watch_id
        self.error: CastError | None = None

    @property
    def active(self) -> bool:
        """Whether the callback is still registered."""
        return self.watch_id in self._component._callbacks

    def cancel(self) -> None:
        """Stop delivering changes to this callback (idempotent)."""
        self._component._cancel_watch(self.watch_id)


class LockGuard:
    """A held lock; a context manager that unlocks on exit (``with self.lock(id): ...``)."""

    def __init__(self, component: Component, address: WorkingMemoryAddress, depth: int) -> None:
        self._component = component
        self.address = address
        self.depth = depth
        self._released = False

    def unlock(self) -> None:
        """Release this lock level (idempotent)."""
        if not self._released:
            self._released = True
            self._component.unlock(self.address.id, subarchitecture=self.address.subarchitecture)

    def __enter__(self) -> LockGuard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.unlock()


class Component:
    """What every component can do; subclass :class:`UnmanagedComponent` or :class:`ManagedComponent`."""

    kind = "unmanaged"
    max_pending_callbacks = 10_000
    """How many callbacks may wait for the dispatcher before delivery backs off (see Dispatcher)."""

    # ------------------------------------------------------------ lifecycle

    def configure(self, args: dict[str, Any]) -> None:
        """Called first with the component's ``args`` from the configuration."""

    def start(self) -> None:
        """Called after configure, before run: register callbacks here."""

    def run(self) -> None:
        """The main loop; by default waits until the component is stopped."""
        self.wait_for_stop()

    def stop(self) -> None:
        """Called once on shutdown (SIGINT/SIGTERM or ``request_stop``)."""

    # -------------------------------------------------------------- binding

    def _cast_bind(self, transport: Transport, language: str = "python") -> None:
        """Attach to a working memory system (done by the runner, not by users)."""
        self._transport = transport
        self._state = ComponentState.STARTING
        # Registering first: the server's answer says who this component is (cast.client.session).
        transport.start_session(language, self.kind, lambda: self._state)
        self._identity: Identity = transport.identity
        self._dispatcher = Dispatcher(self._identity.component_id, self.max_pending_callbacks)
        self._dispatcher.on_space = transport.pump
        # watch id -> (callback, handle, dispatcher priority, latest delivery)
        self._callbacks: dict[int, tuple[Callable[[WorkingMemoryChange], None], WatchHandle, int, bool]] = {}
        self._latest = LatestSlots()
        self._watch_ids = itertools.count(1)
        self._registered_types: set[tuple[str, str]] = set()  # (type, SA) the SA's server was told of
        self._schema_lock = threading.Lock()
        self._stopping = threading.Event()
        # In process, events arrive on the writer's thread, which must never block.
        self._block_on_full = not transport.delivers_on_writer_thread
        self._id_prefix = f"{self._identity.component_id}:{secrets.token_hex(3)}:"
        self._id_counter = itertools.count(1)
        transport.set_event_sink(self._on_event, self._on_watch_error, self._dispatcher.room, self._dispatcher)

    def _set_state(self, state: ComponentState) -> None:
        """Change the life stage the directory shows, and report it at once."""
        self._state = state
        self._transport.report_state()

    def _cast_close(self) -> None:
        self._dispatcher.stop()
        self._transport.close()

    @property
    def component_id(self) -> str:
        """This component's id."""
        return self._identity.component_id

    @property
    def subarchitecture(self) -> str:
        """This component's own subarchitecture."""
        return self._identity.subarchitecture

    @property
    def privileged(self) -> bool:
        """Whether this component may write every SA."""
        return self._identity.privileged

    @property
    def running(self) -> bool:
        """False once the component has been asked to stop."""
        return not self._stopping.is_set()

    def wait_for_stop(self, timeout: float | None = None) -> bool:
        """Sleep until asked to stop (True) or ``timeout`` seconds pass (False); use in run() loops."""
        return self._stopping.wait(timeout)

    def request_stop(self) -> None:
        """Ask the runner to stop this component (stop() is then called once)."""
        self._stopping.set()

    @property
    def log(self) -> logging.Logger:
        """A logger named after the component."""
        return logging.getLogger(f"cast.component.{self.component_id}")

    # ------------------------------------------------------------ WM: write

    def new_id(self) -> str:
        """A fresh entry id, unique across components and restarts."""
        return f"{self._id_prefix}{next(self._id_counter)}"

    def _sa(self, subarchitecture: str | None) -> str:
        return subarchitecture or self._identity.subarchitecture

    def _value(self, value: Message | Loan, sa: str) -> tuple[str, bytes | Loan]:
        """:meth:`_serialise`, or a loan as it is (its type was told when it was taken)."""
        if isinstance(value, Loan):
            return value.type_name, value
        return self._serialise(value, sa)

    def _serialise(self, value: Message, sa: str) -> tuple[str, bytes]:
        """The value's type name and bytes; its type told to the server of ``sa`` on the first write there."""
        return self._register(value, sa), value.SerializeToString()

    def _register(self, value: Message, sa: str) -> str:
        """The value's type name, told to the server of ``sa`` on the first write there.

        Only the server that will hold the value is told: a server that hangs or is away cannot hold up
        writes to the others.
        """
        if not isinstance(value, Message):
            raise InvalidArgumentError(
                f"entry values are protobuf messages, got {type(value).__name__}: define a message type for it"
            )
        name = value.DESCRIPTOR.full_name
        if (name, sa) not in self._registered_types:
            with self._schema_lock:
                if (name, sa) not in self._registered_types:
                    self._transport.register_schemas(files_of(value.DESCRIPTOR), sa)
                    self._registered_types.add((name, sa))
        return name

    def loan(self, value: Message, field: str, size: int, *, subarchitecture: str | None = None) -> Loan:
        """The place of ``size`` bytes of ``value``'s ``bytes`` field ``field``, to fill and then write.

        ``value`` has every field set but ``field`` (a top-level, singular
        ``bytes`` field, left empty). Fill ``loan.buffer``, then pass the loan
        to :meth:`add` or :meth:`overwrite` (or their async forms) in place of
        a message, once: on the server's host the bytes are written where the
        server reads them, not copied (``loan.shared``). Close an unwritten
        loan (or use it in a ``with`` block) to give its place back. Batches
        take messages only. InvalidArgumentError for a field that cannot be
        loaned or a negative size (cast.client.loan).
        """
        sa = self._sa(subarchitecture)
        header = loan_header(value, field, size)
        return self._transport.loan(sa, self._register(value, sa), header, size)

    def add(self, entry_id: str, value: Message | Loan, *, subarchitecture: str | None = None) -> WriteResult:
        """Create an entry; AlreadyExistsError if the id is taken. ``value``: a message, or a loan (:meth:`loan`)."""
        sa = self._sa(subarchitecture)
        type_name_, data = self._value(value, sa)
        return self._transport.add(sa, entry_id, type_name_, data)

    def overwrite(
        self,
        entry_id: str,
        value: Message | Loan,
        *,
        subarchitecture: str | None = None,
        expected_version: int | None = None,
    ) -> WriteResult:
        """Replace an entry's value; ConsistencyError if ``expected_version`` is given and differs.

        ``value``: a message, or a loan (:meth:`loan`).
        """
        sa = self._sa(subarchitecture)
        type_name_, data = self._value(value, sa)
        return self._transport.overwrite(sa, entry_id, type_name_, data, expected_version)

    def add_async(
        self, entry_id: str, value: Message | Loan, *, subarchitecture: str | None = None
    ) -> Future[WriteResult]:
        """Create an entry without waiting for the answer: a future of its result.

        Many writes may be in flight at once (no need for a batch to keep the
        link busy); they are applied in call order. Errors (AlreadyExistsError,
        ...) arrive on the future. Over gRPC the future completes on a client
        thread: keep its callbacks short. A callback may write and wait itself
        (the thread runs it once it stopped reading replies).
        """
        sa = self._sa(subarchitecture)
        type_name_, data = self._value(value, sa)
        return self._transport.add_async(sa, entry_id, type_name_, data)

    def overwrite_async(
        self,
        entry_id: str,
        value: Message | Loan,
        *,
        subarchitecture: str | None = None,
        expected_version: int | None = None,
    ) -> Future[WriteResult]:
        """Replace an entry's value without waiting for the answer: a future of its result (as :meth:`add_async`)."""
        sa = self._sa(subarchitecture)
        type_name_, data = self._value(value, sa)
        return self._transport.overwrite_async(sa, entry_id, type_name_, data, expected_version)

    def delete_entry(
        self, entry_id: str, *, subarchitecture: str | None = None, expected_version: int | None = None
    ) -> WriteResult:
        """Delete an entry (its locks go with it).

        ``delete_entry`` is the name in every language (``deleteEntry`` in C++
        and Java), since ``delete`` is a C++ keyword; :meth:`delete` is the
        same call under its original name (docs/design.md section 5).
        """
        return self._transport.delete(self._sa(subarchitecture), entry_id, expected_version)

    delete = delete_entry

    def batch(
        self, operations: Sequence[tuple[str, str, Message | None]], *, subarchitecture: str | None = None
    ) -> list[WriteResult]:
        """Apply ``(operation, id, value)`` writes in order, all or nothing.

        ``operation`` is ``"add"``, ``"overwrite"`` or ``"delete"`` (value None).
        """
        sa = self._sa(subarchitecture)
        ops = []
        for kind, entry_id, value in operations:
            op = Operation[kind.upper()]
            if op is Operation.DELETE:
                ops.append(BatchOp(op, sa, entry_id))
            else:
                if value is None:
                    raise InvalidArgumentError(f"batch {kind} of '{entry_id}' needs a value")
                if isinstance(value, Loan):
                    raise InvalidArgumentError(f"batch {kind} of '{entry_id}' got a loan: a batch takes messages; "
                                               "write a loan with add or overwrite")
                type_name_, data = self._serialise(value, sa)
                ops.append(BatchOp(op, sa, entry_id, type_name_, data))
        return self._transport.batch(ops)

    # ------------------------------------------------------------- WM: read

    def get(self, entry_id: str, cls: type[M], *, subarchitecture: str | None = None) -> M:
        """The value of an entry, as a new ``cls`` object; NotFoundError if missing."""
        record = self._transport.get(self._sa(subarchitecture), entry_id)
        where = f"entry '{entry_id}' in subarchitecture '{record.subarchitecture}'"
        return decode(cls, record.type, record.data, where)

    def get_view(self, entry_id: str, *, subarchitecture: str | None = None) -> ValueView:
        """An entry's value, serialised, as a read-only view that is not a copy (:class:`cast.ValueView`).

        On the server's host a large value is shared memory the server lends
        while the view is held; numpy wraps it or a field of it
        (``view.field(1)``) without copying. Elsewhere it is the bytes received.
        """
        return ValueView(self._transport.get(self._sa(subarchitecture), entry_id))

    def get_entry(self, entry_id: str, cls: type[M], *, subarchitecture: str | None = None) -> Entry[M]:
        """An entry with its version and author (for versioned overwrites)."""
        return entry_of(cls, self._transport.get(self._sa(subarchitecture), entry_id))

    def get_all(self, cls: type[M], *, subarchitecture: str | None = None, limit: int = 0) -> list[Entry[M]]:
        """Every entry of type ``cls``, newest first (at most ``limit`` if given)."""
        records = self._transport.get_by_type(self._sa(subarchitecture), type_name(cls), limit)
        return [entry_of(cls, r) for r in records]

    def exists(self, entry_id: str, *, subarchitecture: str | None = None) -> bool:
        """Whether an entry exists."""
        return self._transport.exists(self._sa(subarchitecture), entry_id)

    # ---------------------------------------------------------------- locks

    def lock(
        self,
        entry_id: str,
        mode: LockMode = LockMode.OD,
        *,
        subarchitecture: str | None = None,
        timeout: float | None = None,
    ) -> LockGuard:
        """Lock an entry, waiting for another holder up to ``timeout`` seconds (None: forever).

        Re-entrant. Use as ``with self.lock(id): ...`` to unlock at the end.
        DeadlineExceededError when the wait times out.
        """
        sa = self._sa(subarchitecture)
        depth = self._transport.lock(sa, entry_id, LockMode(mode), timeout, False)
        return LockGuard(self, WorkingMemoryAddress(entry_id, sa), depth)

    def try_lock(self, entry_id: str, mode: LockMode = LockMode.OD, *, subarchitecture: str | None = None) -> bool:
        """Lock an entry if no other component holds it; never waits."""
        from cast.errors import LockedError

        try:
            self._transport.lock(self._sa(subarchitecture), entry_id, LockMode(mode), None, True)
        except LockedError:
            return False
        return True

    def unlock(self, entry_id: str, *, subarchitecture: str | None = None) -> int:
        """Release one level of this component's lock; return the remaining depth."""
        return self._transport.unlock(self._sa(subarchitecture), entry_id)

    # ------------------------------------------------------------- outcomes

    def report(self, name: str, value: float) -> None:
        """Report a measured outcome (``self.report("answers_correct", 1)``) for experiments to read.

        The server keeps per name the count, sum, min, max and last value of
        what this component reported (``cast stats``, ``cast run
        --summary-json``, ``cast sweep``). InvalidArgumentError for an empty
        name or one over 128 bytes, or a value that is not a finite number;
        ResourceExhaustedError past 256 names. A refused report records nothing.
        """
        try:
            number = float(value)
        except (TypeError, ValueError):
            # As the server words it; a value the wire cannot carry never leaves the component.
            raise InvalidArgumentError(f"report '{name}': the value must be a number, got {value!r}") from None
        self._transport.report(name, number)

    # ------------------------------------------------------------- watching

    def on_change(
        self,
        filters: ChangeFilter | Sequence[ChangeFilter],
        callback: Callable[[WorkingMemoryChange], None],
        *,
        delivery: Delivery | str = Delivery.QUEUE,
        priority: Priority | str = Priority.MEDIUM,
    ) -> WatchHandle:
        """Call ``callback(change)`` on the dispatcher thread for each matching change, in revision order.

        Several filters are ORed. Changes made after this returns are never
        missed. ``delivery="latest"`` is for fast data read by a slower
        callback: of the changes of one entry not yet handed to it, only the
        newest is, with ``change.skipped`` saying how many it replaced (the
        server conflates what waits on its side too). ``priority`` ("high",
        "medium", "low") orders this component's pending callbacks.
        """
        flist = [filters] if isinstance(filters, ChangeFilter) else list(filters)
        if not flist:
            raise InvalidArgumentError("on_change needs at least one filter")
        latest = delivery_of(delivery) is Delivery.LATEST
        level = priority_of(priority)
        watch_id = next(self._watch_ids)
        handle = WatchHandle(self, watch_id)
        self._callbacks[watch_id] = (callback, handle, level, latest)
        try:
            self._transport.watch(watch_id, [f.resolve(self.subarchitecture) for f in flist], latest=latest)
        except BaseException:
            self._callbacks.pop(watch_id, None)
            raise
        return handle

    def _cancel_watch(self, watch_id: int) -> None:
        registered = self._callbacks.pop(watch_id, None)
        if registered is not None:
            self._transport.cancel_watch(watch_id)
            if registered[3]:
                self._latest.drop(watch_id)

    def _on_event(self, event: ChangeEvent, watch_ids: Sequence[int]) -> None:
        for wid in watch_ids:
            registered = self._callbacks.get(wid)
            if registered is None:
                continue
            change = WorkingMemoryChange(event)  # one each: a latest watch's counts are its own
            if registered[3]:
                key = (wid, event.subarchitecture, event.id)
                if self._latest.offer(key, change):
                    self._dispatcher.submit(self._deliver_latest, wid, key, block=False, priority=registered[2])
            else:
                self._dispatcher.submit(self._deliver, wid, change, block=self._block_on_full, priority=registered[2])

    def _deliver(self, watch_id: int, change: WorkingMemoryChange) -> None:
        registered = self._callbacks.get(watch_id)
        if registered is not None:  # cancelled while queued: drop
            registered[0](change)

    def _deliver_latest(self, watch_id: int, key: tuple[int, str, str]) -> None:
        change = self._latest.take(key)  # the newest by now, whatever arrived since this was queued
        if change is not None:
            self._deliver(watch_id, change)

    def _on_watch_error(self, error: CastError) -> None:
        for _, handle, _, _ in list(self._callbacks.values()):
            handle.error = error
        self._dispatcher.submit(self.watch_failed, error)

    def watch_failed(self, error: CastError) -> None:
        """Called (on the dispatcher) when change delivery stopped, e.g. HistoryExpiredError.

        The default logs it. Override to resynchronise: read the current state,
        then register the callbacks again.
        """
        log.error("%s: change delivery stopped: %s", self.component_id, error)

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every callback queued so far has run (tests, orderly shutdown)."""
        return self._dispatcher.drain(timeout)


class UnmanagedComponent(Component):
    """A component that runs continuously and pushes its results to working memory."""

    kind = "unmanaged"


class ManagedComponent(Component):
    """A component whose expensive work runs as tasks its SA's task manager adopts."""

    kind = "managed"

    def _cast_bind(self, transport: Transport, language: str = "python") -> None:
        super()._cast_bind(transport, language)
        transport.set_decision_sink(self._on_decision)

    def _on_decision(self, record: TaskRecord) -> None:
        task = Task(record)
        if record.state is TaskState.ADOPTED:
            self._dispatcher.submit(self.task_adopted, task)
        elif record.state is TaskState.REJECTED:
            self._dispatcher.submit(self.task_rejected, task)

    def propose_task(self, name: str, data: Message | None = None, *, priority: int = 0) -> Task:
        """Propose a task to the own SA's task manager; the decision arrives in a hook."""
        type_name_, payload = ("", b"") if data is None else self._serialise(data, self._identity.subarchitecture)
        return Task(self._transport.propose(name, type_name_, payload, priority))

    def retract_task(self, task: Task | str) -> None:
        """Withdraw a waiting or adopted task."""
        self._transport.retract(task if isinstance(task, str) else task.task_id)

    def task_complete(self, task: Task | str, outcome: TaskOutcome = TaskOutcome.SUCCEEDED, reason: str = "") -> None:
        """Report that an adopted task ended, with its outcome."""
        self._transport.complete(task if isinstance(task, str) else task.task_id, outcome, reason)

    def task_adopted(self, task: Task) -> None:
        """Hook: the task manager adopted ``task``; do the work, then call task_complete."""

    def task_rejected(self, task: Task) -> None:
        """Hook: the task manager rejected ``task``."""
