"""Durable working memories: a write-ahead journal of every commit on SQLite (WAL).

The host calls :meth:`Journal.append` under its mutex with the events of one
commit; that only queues them (a list append), so the host's critical section
never waits for the disk. A committer thread writes queued commits to SQLite:

- ``always``: one transaction (commit + fsync) per write call, in order;
- ``batch``: everything queued so far in one transaction (group commit);
- ``none``: like ``batch`` but with ``synchronous=OFF`` and nobody waits: the
  file is a best-effort copy (complete after a clean shutdown).

A caller that must not acknowledge a write before it is durable takes
:meth:`Journal.ticket` after its write returned and waits for it
(:meth:`Journal.wait` on a thread, :meth:`Journal.wait_async` on an event
loop). Tickets are a counter of appended commits, so waiting for the current
ticket covers the caller's own commit and perhaps a few more of the same group.

After each transaction, and before it releases the waiters, the committer hands
the events it made durable to :attr:`Journal.on_durable` (the host's
``apply_durable``): in ``always`` and ``batch`` that is when a write becomes
visible. A journal that fails makes nothing more visible.

The file also keeps the version floor (:mod:`cast.core.versions`): unchanged
across restarts that lose nothing, raised to an epoch floor when a crash in
``none`` may have lost writes that others saw.

Fault injection for tests: :meth:`Journal.hold` keeps the committer from
writing until :meth:`Journal.release`; with ``CAST_FAILPOINT_JOURNAL_HOLD=PATH``
in the environment it also waits while that file exists (for a server in
another process), and ``CAST_FAILPOINT_JOURNAL_DELAY_MS=N`` makes it wait N ms
before each transaction, as a slow disk would.

The file holds the state (entries, last versions of deleted entries, revision
counters, registered schemas) and the last ``history_events`` events per WM,
so that after a restart the revision counters continue and a watcher may resume
from a revision the history still covers. Locks and sessions are not kept: a
restart ends every session, so whatever they held is released.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import os
import secrets
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from cast.core.records import ChangeEvent, EntryRecord, Operation
from cast.core.versions import epoch_floor
from cast.errors import InternalError

__all__ = ["Durability", "Journal", "StoredState", "WMState"]

log = logging.getLogger("cast.journal")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS revisions (sa TEXT PRIMARY KEY, revision INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS entries (
  sa TEXT NOT NULL, id TEXT NOT NULL, type TEXT NOT NULL, data BLOB NOT NULL, version INTEGER NOT NULL,
  author TEXT NOT NULL, modified_ns INTEGER NOT NULL, revision INTEGER NOT NULL, PRIMARY KEY (sa, id));
CREATE TABLE IF NOT EXISTS deleted (sa TEXT NOT NULL, id TEXT NOT NULL, version INTEGER NOT NULL, PRIMARY KEY (sa, id));
CREATE TABLE IF NOT EXISTS events (
  seq INTEGER PRIMARY KEY, sa TEXT NOT NULL, revision INTEGER NOT NULL, op INTEGER NOT NULL, id TEXT NOT NULL,
  type TEXT NOT NULL, source_component TEXT NOT NULL, source_sa TEXT NOT NULL, version INTEGER NOT NULL,
  time_ns INTEGER NOT NULL, data BLOB NOT NULL, author TEXT NOT NULL, modified_ns INTEGER NOT NULL,
  entry_revision INTEGER NOT NULL, odr_holder TEXT);
CREATE INDEX IF NOT EXISTS events_by_sa ON events (sa, revision);
CREATE TABLE IF NOT EXISTS schemas (name TEXT PRIMARY KEY, data BLOB NOT NULL);
"""


class Durability(enum.Enum):
    """When a write is acknowledged (``persistence.durability`` in the configuration)."""

    ALWAYS = "always"
    BATCH = "batch"
    NONE = "none"


@dataclass
class WMState:
    """What the journal holds of one working memory."""

    revision: int = 0
    entries: list[EntryRecord] = field(default_factory=list)  # oldest write first
    deleted: dict[str, int] = field(default_factory=dict)  # id -> last version
    events: list[ChangeEvent] = field(default_factory=list)  # the newest events, by revision


@dataclass
class StoredState:
    """Everything read back from a journal file."""

    history_id: str
    wms: dict[str, WMState]
    schemas: list[bytes]  # serialised FileDescriptorProto, in registration order
    clean: bool  # the previous run closed the journal (no crash)
    version_floor: int = 0  # the lowest version this run may give (cast.core.versions)


_Item = tuple[str, object]  # ("events", list[ChangeEvent]) or ("schemas", list[(name, bytes)])


class Journal:
    """The journal file of one server; thread-safe; one committer thread."""

    def __init__(self, path: str | Path, durability: Durability | str, history_events: int = 65_536) -> None:
        self.path = Path(path)
        self.durability = Durability(durability)
        self.waits = self.durability is not Durability.NONE  # whether writers wait for the disk
        self._history_events = max(1, history_events)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        # FULL: the WAL is fsynced at every commit, so a committed write survives a crash of the
        # machine, not only of the process. OFF for `none`: the OS flushes when it likes.
        self._db.execute(f"PRAGMA synchronous={'OFF' if self.durability is Durability.NONE else 'FULL'}")
        self._db.executescript(_SCHEMA)
        self._cond = threading.Condition()
        self._queue: list[_Item] = []
        self._appended = 0  # tickets handed out
        self._durable = 0  # tickets written (and fsynced unless `none`)
        self._failure: BaseException | None = None
        self._closing = False
        self._async_waiters: list[tuple[int, asyncio.AbstractEventLoop, asyncio.Future[None]]] = []
        self._since_trim = 0
        self._last_rev: dict[str, int] = {}
        self.commits = 0  # transactions made (for tests and figures)
        self.on_durable: Callable[[list[ChangeEvent]], None] | None = None
        self._held = False
        self._hold_file = os.environ.get("CAST_FAILPOINT_JOURNAL_HOLD", "")
        self._delay_s = float(os.environ.get("CAST_FAILPOINT_JOURNAL_DELAY_MS") or 0) / 1000
        self._open_run()
        self._committer = threading.Thread(target=self._run, name="cast-journal", daemon=True)
        self._committer.start()

    def _open_run(self) -> None:
        """Decide this run's history id and version floor, and mark the file in use (durably)."""
        db = self._db
        row = db.execute("SELECT value FROM meta WHERE key = 'history_id'").fetchone()
        clean = db.execute("SELECT value FROM meta WHERE key = 'clean'").fetchone()
        floor_row = db.execute("SELECT value FROM meta WHERE key = 'version_floor'").fetchone()
        self.was_clean = clean is None or clean[0] == "1"
        self.version_floor = int(floor_row[0]) if floor_row is not None else 0
        lost = self.durability is Durability.NONE and not self.was_clean
        if row is None or lost:
            # A new file, or a crash in a mode that may have lost acknowledged writes: watchers
            # that saw those writes must not resume into a history that no longer has them.
            self.history_id = secrets.token_hex(8)
        else:
            self.history_id = str(row[0])
        if lost:
            # Versions the lost writes gave were seen: start above them, and above every stored one.
            (stored,) = db.execute(
                "SELECT max(v) FROM (SELECT max(version) AS v FROM entries UNION ALL "
                "SELECT max(version) FROM deleted)"
            ).fetchone()
            self.version_floor = epoch_floor(above=max(self.version_floor, stored or 0))
        # The floor must be on disk before any version above it is given, whatever the mode.
        db.execute("PRAGMA synchronous=FULL")
        db.execute("BEGIN")
        db.execute("INSERT OR REPLACE INTO meta VALUES ('history_id', ?)", (self.history_id,))
        db.execute("INSERT OR REPLACE INTO meta VALUES ('version_floor', ?)", (str(self.version_floor),))
        db.execute("INSERT OR REPLACE INTO meta VALUES ('clean', '0')")
        db.execute("COMMIT")
        if self.durability is Durability.NONE:
            db.execute("PRAGMA synchronous=OFF")

    # ------------------------------------------------------------- reading

    def load(self) -> StoredState:
        """Read back the state (call before any append)."""
        db = self._db
        wms: dict[str, WMState] = {}
        for sa, revision in db.execute("SELECT sa, revision FROM revisions"):
            wms[sa] = WMState(revision=revision)
        rows = db.execute(
            "SELECT sa, id, type, data, version, author, modified_ns, revision FROM entries ORDER BY revision"
        )
        for sa, id_, type_, data, version, author, modified, revision in rows:
            wms.setdefault(sa, WMState()).entries.append(
                EntryRecord(sa, id_, type_, bytes(data), version, author, modified, revision)
            )
        for sa, id_, version in db.execute("SELECT sa, id, version FROM deleted"):
            wms.setdefault(sa, WMState()).deleted[id_] = version
        rows = db.execute(
            "SELECT seq, sa, revision, op, id, type, source_component, source_sa, version, time_ns, data, author, "
            "modified_ns, entry_revision, odr_holder FROM events ORDER BY seq"
        )
        for seq, sa, rev, op, id_, type_, src, src_sa, version, time_ns, data, author, modified, erev, odr in rows:
            record = EntryRecord(sa, id_, type_, bytes(data), version, author, modified, erev)
            wms.setdefault(sa, WMState()).events.append(
                ChangeEvent(seq, rev, Operation(op), sa, id_, type_, src, src_sa, version, time_ns, record, odr)
            )
        schemas = [bytes(d) for (d,) in db.execute("SELECT data FROM schemas ORDER BY rowid")]
        for sa, state in wms.items():
            self._last_rev[sa] = state.revision
        return StoredState(self.history_id, wms, schemas, self.was_clean, self.version_floor)

    # ------------------------------------------------------------- writing

    def append(self, events: list[ChangeEvent]) -> None:
        """Queue the events of one commit (called under the host's mutex: no I/O here)."""
        with self._cond:
            self._queue.append(("events", events))
            self._appended += 1
            self._cond.notify()

    def forget_schemas(self, names: Iterable[str]) -> None:
        """Delete stored schema files the registry no longer loads (call before any append)."""
        with self._cond:
            self._db.executemany("DELETE FROM schemas WHERE name = ?", [(name,) for name in names])

    def append_schemas(self, files: Iterable[tuple[str, bytes]]) -> None:
        """Queue newly registered schema files ``(name, serialised FileDescriptorProto)``."""
        with self._cond:
            self._queue.append(("schemas", list(files)))
            self._appended += 1
            self._cond.notify()

    def ticket(self) -> int:
        """The ticket of the newest commit appended so far."""
        return self._appended

    def durable(self) -> int:
        """The newest ticket that is on disk."""
        return self._durable

    def hold(self) -> None:
        """Fault injection: stop writing (appends queue up, waiters wait) until :meth:`release`."""
        with self._cond:
            self._held = True

    def release(self) -> None:
        """Undo :meth:`hold`."""
        with self._cond:
            self._held = False
            self._cond.notify_all()

    def wait(self, ticket: int, timeout: float | None = None) -> None:
        """Block until ``ticket`` is durable; InternalError if the journal failed."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._durable >= ticket or self._failure is not None, timeout):
                raise InternalError(f"the journal did not make write {ticket} durable within {timeout} s")
            self._raise_failure()

    async def wait_async(self, ticket: int) -> None:
        """Wait on the event loop until ``ticket`` is durable; InternalError if the journal failed."""
        loop = asyncio.get_running_loop()
        with self._cond:
            self._raise_failure()
            if self._durable >= ticket:
                return
            fut: asyncio.Future[None] = loop.create_future()
            self._async_waiters.append((ticket, loop, fut))
        await fut

    def _raise_failure(self) -> None:
        if self._failure is not None:
            raise InternalError(
                f"the write was applied in memory but the journal {self.path} could not store it "
                f"({self._failure}): it will not survive a restart; fix the disk and restart the server"
            )

    # ----------------------------------------------------------- committer

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: (bool(self._queue) and not self._held) or self._closing)
                if not self._queue and self._closing:
                    return
            self._failpoints()
            with self._cond:
                if self.durability is Durability.ALWAYS:
                    items = [self._queue.pop(0)]
                else:
                    items, self._queue = self._queue, []
            try:
                if self._failure is None:
                    self._write(items)
                    self._made_durable(items)
            except Exception as exc:  # every waiter is told; the server keeps serving reads
                log.exception("journal %s failed", self.path)
                with self._cond:
                    self._failure = exc
            with self._cond:
                self._durable += len(items)
                done = self._durable
                ready = [w for w in self._async_waiters if w[0] <= done or self._failure is not None]
                self._async_waiters = [w for w in self._async_waiters if w not in ready]
                self._cond.notify_all()
            failure = self._failure
            for _, loop, fut in ready:
                with contextlib.suppress(RuntimeError):  # the loop is closed: nobody waits any more
                    loop.call_soon_threadsafe(_settle, fut, failure)

    def _failpoints(self) -> None:
        # Fault injection across processes (see the module docstring); a poll is enough for tests.
        while self._hold_file and os.path.exists(self._hold_file) and not self._closing:
            time.sleep(0.005)
        if self._delay_s:
            time.sleep(self._delay_s)

    def _made_durable(self, items: list[_Item]) -> None:
        if self.on_durable is None:
            return
        events: list[ChangeEvent] = []
        for kind, payload in items:
            if kind == "events":
                events.extend(payload)  # type: ignore[arg-type]
        if events:
            self.on_durable(events)

    def _write(self, items: list[_Item]) -> None:
        db = self._db
        db.execute("BEGIN")
        try:
            for kind, payload in items:
                if kind == "schemas":
                    db.executemany("INSERT OR IGNORE INTO schemas VALUES (?, ?)", payload)  # type: ignore[arg-type]
                else:
                    self._write_events(payload)  # type: ignore[arg-type]
            self._maybe_trim()
            db.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            raise
        self.commits += 1

    def _write_events(self, events: list[ChangeEvent]) -> None:
        db = self._db
        for ev in events:
            rec = ev.entry
            assert rec is not None  # the host always keeps the record with the event
            db.execute(
                "INSERT INTO events (sa, revision, op, id, type, source_component, source_sa, version, time_ns, "
                "data, author, modified_ns, entry_revision, odr_holder) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (ev.subarchitecture, ev.revision, int(ev.operation), ev.id, ev.type, ev.source_component,
                 ev.source_subarchitecture, ev.version, ev.time_ns, rec.data, rec.author, rec.modified_ns,
                 rec.revision, ev.odr_holder),
            )
            if ev.operation is Operation.DELETE:
                db.execute("DELETE FROM entries WHERE sa = ? AND id = ?", (ev.subarchitecture, ev.id))
                db.execute("INSERT OR REPLACE INTO deleted VALUES (?, ?, ?)", (ev.subarchitecture, ev.id, ev.version))
            else:
                db.execute(
                    "INSERT OR REPLACE INTO entries VALUES (?,?,?,?,?,?,?,?)",
                    (rec.subarchitecture, rec.id, rec.type, rec.data, rec.version, rec.author, rec.modified_ns,
                     rec.revision),
                )
                db.execute("DELETE FROM deleted WHERE sa = ? AND id = ?", (ev.subarchitecture, ev.id))
            db.execute("INSERT OR REPLACE INTO revisions VALUES (?, ?)", (ev.subarchitecture, ev.revision))
            self._last_rev[ev.subarchitecture] = ev.revision
            self._since_trim += 1

    def _maybe_trim(self) -> None:
        # The events table is the history ring on disk: keep the newest history_events per WM,
        # trimming now and then rather than on every write.
        if self._since_trim < max(1024, self._history_events // 8):
            return
        self._since_trim = 0
        for sa, last in self._last_rev.items():
            self._db.execute("DELETE FROM events WHERE sa = ? AND revision <= ?", (sa, last - self._history_events))

    # ------------------------------------------------------------ shutdown

    def close(self) -> None:
        """Write everything queued, mark the file cleanly closed, stop the committer."""
        with self._cond:
            if self._closing:
                return
            self._closing = True
            self._cond.notify_all()
        self._committer.join()
        if self._failure is None:
            self._db.execute("INSERT OR REPLACE INTO meta VALUES ('clean', '1')")
        self._db.close()


def _settle(fut: asyncio.Future[None], failure: BaseException | None) -> None:
    if fut.done():
        return
    if failure is None:
        fut.set_result(None)
    else:
        fut.set_exception(
            InternalError(f"the write was applied in memory but could not be stored durably ({failure})")
        )
