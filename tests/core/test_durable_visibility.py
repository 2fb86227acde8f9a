"""Only durable state is visible: a write held back by the journal is seen by nobody.

The journal's fault-injection hook (`Journal.hold`) keeps its committer from
writing, so a write is committed in memory but not durable for as long as the
test wants, with no sleep deciding anything. While it is held, no other caller
may observe the write: not a read, not a type read's revision, not a watcher,
not the details of a refused compare-and-set, not a lock grant, not a task
decision. Calls that would have to tell of it answer only after the release.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from cast.core.access import Access, run_sync
from cast.core.journal import Journal
from cast.core.policies import make_policy
from cast.core.records import BatchOp, Identity, LockMode, Operation
from cast.core.system import TASK_TYPE, System
from cast.core.watch import EventFilter, Subscription
from cast.errors import CastError, ConsistencyError, NotFoundError

W = Identity("writer", "vision")
R = Identity("reader", "vision")
T = "t.T"


@pytest.fixture(params=["always", "batch"])
def system(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[System]:
    journal = Journal(tmp_path / "wm.db", request.param)
    s = System("t", ["vision"], {"vision": make_policy("fifo", {"max_concurrent": 1})}, journal=journal)
    for who in (W, R):  # locks and tasks need a live session
        s.sessions.register(who, "python", "unmanaged", 0, "")
    _SYSTEM[:] = [s]
    yield s
    assert s.journal is not None
    s.journal.release()
    s.close()


class Call:
    """A call on its own thread, as another component would make it."""

    def __init__(self, fn: Callable[[], Any]) -> None:
        self.result: Any = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(fn,), daemon=True)
        self.thread.start()

    def _run(self, fn: Callable[[], Any]) -> None:
        try:
            self.result = fn()
        except BaseException as exc:  # handed to the test
            self.error = exc

    def pending(self) -> bool:
        """Still waiting: give it a moment to answer wrongly before saying so."""
        self.thread.join(0.3)
        return self.thread.is_alive()

    def done(self) -> Any:
        self.thread.join(10)
        assert not self.thread.is_alive(), "the call did not return after the journal was released"
        if self.error is not None:
            raise self.error
        return self.result


def _write(who: Identity, op: Operation, entry_id: str, data: bytes = b"", expected: int | None = None) -> Call:
    """A write by ``who`` through its Access, on its own thread."""
    system = _SYSTEM[0]
    return Call(lambda: run_sync(system, Access(system, who).write(BatchOp(op, "vision", entry_id, T, data, expected))))


_SYSTEM: list[System] = []


def _held(system: System) -> Journal:
    assert system.journal is not None
    system.journal.hold()
    return system.journal


def test_a_held_write_is_invisible_to_reads_watchers_and_refusals(system: System) -> None:
    host = system.host
    host.add(W, "vision", "x", T, b"v0")
    system.durable_sync()
    seen: list[int] = []
    sub = Subscription(host, lambda: seen.extend(m.event.revision for m in sub.poll()))
    sub.add_watch(1, [EventFilter()])
    revision = host.revision("vision")
    journal = _held(system)

    write = _write(W, Operation.OVERWRITE, "x", b"v1")
    assert write.pending(), "the writer was answered before its write was durable"
    # Committed in memory, not durable: nobody else sees it.
    assert host.pending_writes() == 1
    assert host.get(R, "vision", "x").data == b"v0"
    assert host.get(R, "vision", "x").version == 0
    records, type_revision = host.get_by_type(R, "vision", T)
    assert [r.data for r in records] == [b"v0"] and type_revision == revision
    assert host.revisions() == {"vision": revision}
    assert seen == []
    # A compare-and-set against the held write is refused, but only once it is durable, and
    # its refusal names the durable version then; a lock on it waits the same way.
    cas = _write(R, Operation.OVERWRITE, "x", b"r", expected=0)
    lock = Call(lambda: run_sync(system, Access(system, R).lock("vision", "x", LockMode.O, no_wait=True)))
    assert cas.pending() and lock.pending()
    assert host.get(R, "vision", "x").data == b"v0"

    journal.release()
    assert write.done().version == 1
    with pytest.raises(ConsistencyError, match="at version 1, expected 0"):
        cas.done()
    assert lock.done() == 1
    assert host.get(R, "vision", "x").data == b"v1"
    assert seen == [revision + 1]
    assert host.pending_writes() == 0
    sub.close()


def test_a_held_add_and_delete_are_invisible(system: System) -> None:
    host = system.host
    host.add(W, "vision", "gone", T, b"g")
    system.durable_sync()
    journal = _held(system)
    add = _write(W, Operation.ADD, "new", b"n")
    delete = _write(W, Operation.DELETE, "gone")
    assert add.pending() and delete.pending()
    assert not host.exists(R, "vision", "new")
    assert host.exists(R, "vision", "gone")
    with pytest.raises(NotFoundError):
        host.get(R, "vision", "new")
    assert host.get(R, "vision", "gone").data == b"g"
    assert host.entry_count("vision") == 1
    # A second write of the held entry is checked against the latest state: the versions go on.
    again = _write(W, Operation.OVERWRITE, "new", b"n2")
    readd = _write(W, Operation.ADD, "gone", b"g2")
    assert again.pending() and readd.pending()
    journal.release()
    assert add.done().version == 0
    assert again.done().version == 1
    assert delete.done().version == 0
    assert readd.done().version == 1
    assert host.get(R, "vision", "new").data == b"n2"
    assert host.get(R, "vision", "gone").version == 1


def test_a_held_batch_is_all_invisible_then_all_visible(system: System) -> None:
    host = system.host
    journal = _held(system)
    ops = [BatchOp(Operation.ADD, "vision", f"b{i}", T, b"x") for i in range(3)]
    batch = Call(lambda: run_sync(system, Access(system, W).batch(ops)))
    assert batch.pending()
    assert [host.exists(R, "vision", f"b{i}") for i in range(3)] == [False] * 3
    journal.release()
    assert [r.version for r in batch.done()] == [0, 0, 0]
    assert [host.exists(R, "vision", f"b{i}") for i in range(3)] == [True] * 3


def test_a_task_decision_is_handed_out_only_once_its_write_is_durable(system: System) -> None:
    decided: list[str] = []
    system.tasks.add_listener(lambda comp: decided.extend(t.task_id for t in system.tasks.take_decisions(comp)))
    journal = _held(system)
    propose = Call(lambda: run_sync(system, Access(system, W).propose("work")))
    assert propose.pending()
    assert decided == []
    assert system.host.get_by_type(R, "vision", TASK_TYPE)[0] == []
    journal.release()
    task = propose.done()
    assert decided == [task.task_id]
    assert [r.id for r in system.host.get_by_type(R, "vision", TASK_TYPE)[0]] == [task.task_id]


def test_a_failed_journal_makes_nothing_more_visible(system: System) -> None:
    host = system.host
    host.add(W, "vision", "x", T, b"v0")
    system.durable_sync()
    journal = system.journal
    assert journal is not None

    def broken(items: object) -> None:
        raise OSError("disk full (injected)")

    journal._write = broken  # type: ignore[method-assign]
    with pytest.raises(CastError, match="could not store it"):
        run_sync(system, Access(system, W).write(BatchOp(Operation.OVERWRITE, "vision", "x", T, b"v1")))
    assert host.get(R, "vision", "x").data == b"v0"
