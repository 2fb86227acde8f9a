"""The rule list of docs/guarantees.md, walked once per transport (gRPC and in process, memory and journal).

Each rule is a small function of the component factory; the test runs every rule
against every transport of ``make_component`` (tests/client/conftest.py), so a
rule that holds one way and not the other fails by name.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from cast_testing_pb2 import Counter, Pose

import cast
from cast.core.access import Access
from cast.core.records import Identity
from tests.client.test_component_api import Manager, wait_for

Rule = Callable[[Any], None]
RULES: dict[str, Rule] = {}


def rule(fn: Rule) -> Rule:
    RULES[fn.__name__] = fn
    return fn


def _two(make: Any) -> tuple[Any, Any]:
    return make(cast.UnmanagedComponent, "a"), make(cast.UnmanagedComponent, "b")


@rule
def versions_count_writes_from_the_add(make: Any) -> None:
    a, _ = _two(make)
    v0 = a.add("x", Counter(value=1)).version
    assert a.overwrite("x", Counter(value=2)).version == v0 + 1
    assert a.delete_entry("x").version == v0 + 1
    assert a.add("x", Counter()).version == v0 + 2  # a re-add continues


@rule
def an_expected_version_mismatch_is_a_consistency_error_and_changes_nothing(make: Any) -> None:
    a, b = _two(make)
    v0 = a.add("x", Counter(value=1)).version
    b.overwrite("x", Counter(value=2), expected_version=v0)
    with pytest.raises(cast.ConsistencyError, match=f"at version {v0 + 1}, expected {v0}"):
        a.overwrite("x", Counter(value=3), expected_version=v0)
    with pytest.raises(cast.ConsistencyError):
        a.delete_entry("x", expected_version=v0)
    assert a.get("x", Counter).value == 2


@rule
def unprivileged_writes_stay_in_their_own_sa_and_reads_are_open(make: Any) -> None:
    a, _ = _two(make)
    other = make(cast.UnmanagedComponent, "l", "language")
    other.add("mine", Counter())
    with pytest.raises(cast.PermissionDeniedError, match="component 'a' \\(SA 'vision'\\)"):
        a.add("y", Counter(), subarchitecture="language")
    assert a.exists("mine", subarchitecture="language")
    boss = make(cast.UnmanagedComponent, "boss", "language", privileged=True)
    boss.add("from-boss", Counter(), subarchitecture="vision")


@rule
def each_lock_mode_stops_others_and_names_its_holder(make: Any) -> None:
    a, b = _two(make)
    for mode, stops in ((cast.LockMode.O, ("overwrite",)), (cast.LockMode.OD, ("overwrite", "delete")),
                        (cast.LockMode.ODR, ("overwrite", "delete", "read"))):
        entry = f"x-{mode.name}"
        a.add(entry, Counter())
        with a.lock(entry, mode):
            for action in stops:
                with pytest.raises(cast.LockedError, match=f"locked \\({mode.name}\\) by component 'a'"):
                    if action == "overwrite":
                        b.overwrite(entry, Counter(value=9))
                    elif action == "delete":
                        b.delete_entry(entry)
                    else:
                        b.get(entry, Counter)
            assert not b.try_lock(entry)


@rule
def locks_are_reentrant_and_released_by_the_holder_or_a_delete(make: Any) -> None:
    a, b = _two(make)
    a.add("x", Counter())
    assert a.try_lock("x") and a.try_lock("x")
    a.unlock("x")
    assert not b.try_lock("x")
    a.unlock("x")
    assert b.try_lock("x")
    b.delete_entry("x")  # the holder's delete releases its lock
    assert not a.exists("x")


@rule
def a_blocking_lock_gives_up_at_its_deadline(make: Any) -> None:
    a, b = _two(make)
    a.add("x", Counter())
    # Over gRPC the client's deadline and the server's may pass together: the class is the rule.
    with a.lock("x", cast.LockMode.O), pytest.raises(cast.DeadlineExceededError):
        b.lock("x", cast.LockMode.O, timeout=0.2)


@rule
def a_batch_is_all_or_nothing_and_names_the_failing_operation(make: Any) -> None:
    a, _ = _two(make)
    with pytest.raises(cast.NotFoundError, match="batch operation 1"):
        a.batch([("add", "p", Counter()), ("overwrite", "missing", Counter())])
    assert not a.exists("p")


@rule
def task_entries_are_written_by_the_server_only(make: Any) -> None:
    m = make(Manager, "m")
    m.start()
    task = m.propose_task("work")
    wait_for(lambda: len(m.decisions) == 1)
    with pytest.raises(cast.PermissionDeniedError, match="belong to the server"):
        m.delete_entry(task.task_id)


@rule
def completing_a_task_needs_an_outcome_and_only_the_proposer_may(make: Any) -> None:
    m = make(Manager, "m")
    other = make(Manager, "other")
    m.start()
    task = m.propose_task("work")
    wait_for(lambda: len(m.decisions) == 1)
    with pytest.raises(cast.InvalidArgumentError, match="needs an outcome"):
        m.task_complete(task, cast.TaskOutcome.UNSPECIFIED)
    with pytest.raises(cast.PermissionDeniedError):
        other.task_complete(task)
    m.task_complete(task)


@rule
def events_come_once_in_revision_order_with_the_entry_only_when_asked(make: Any) -> None:
    a, b = _two(make)
    plain: list[cast.WorkingMemoryChange] = []
    b.on_change(cast.local_type_filter(Counter), plain.append)
    full = make(cast.UnmanagedComponent, "full")
    rich: list[cast.WorkingMemoryChange] = []
    full.on_change(cast.local_type_filter(Counter, include_entry=True), rich.append)
    for i in range(5):
        a.add(f"e{i}", Counter(value=i))
    wait_for(lambda: len(plain) == 5 and len(rich) == 5)
    assert [c.revision for c in plain] == sorted({c.revision for c in plain})
    assert not any(c.has_entry for c in plain)
    assert [c.entry(Counter).value.value for c in rich] == list(range(5))


@rule
def an_entry_written_under_an_odr_lock_reaches_others_without_its_value(make: Any) -> None:
    a, _ = _two(make)
    full = make(cast.UnmanagedComponent, "full")
    rich: list[cast.WorkingMemoryChange] = []
    full.on_change(cast.address_filter("s", include_entry=True), rich.append)
    a.add("s", Pose(label="open"))
    with a.lock("s", cast.LockMode.ODR):
        a.overwrite("s", Pose(label="secret"))
    wait_for(lambda: len(rich) == 2)
    assert rich[0].has_entry and not rich[1].has_entry


@rule
def values_are_copies(make: Any) -> None:
    a, _ = _two(make)
    value = Pose(label="before")
    a.add("c", value)
    value.label = "after"
    read = a.get("c", Pose)
    assert read.label == "before"
    read.label = "changed"
    assert a.get("c", Pose).label == "before"


@rule
def bad_input_is_refused_by_name(make: Any) -> None:
    a, _ = _two(make)
    with pytest.raises(cast.InvalidArgumentError, match="entry id is empty"):
        a.add("", Counter())
    with pytest.raises(cast.NotFoundError, match="no subarchitecture 'atlantis'"):
        a.get("x", Counter, subarchitecture="atlantis")
    with pytest.raises(cast.AlreadyExistsError):
        a.add("dup", Counter())
        a.add("dup", Counter())




@rule
def completing_a_waiting_task_is_a_task_state_error_over_any_transport(make: Any) -> None:
    from cast.errors import TaskStateError

    m = make(Manager, "m")
    m.start()
    first = m.propose_task("first")
    second = m.propose_task("second")  # fifo, one at a time: it waits
    wait_for(lambda: len(m.decisions) == 1)
    with pytest.raises(TaskStateError, match="waiting, not adopted") as err:
        m.task_complete(second)
    assert isinstance(err.value, cast.LockedError)  # and still the FAILED_PRECONDITION family
    m.task_complete(first)


@rule
def a_session_ends_with_its_component_and_releases_its_locks(make: Any) -> None:
    a, b = _two(make)
    a.add("x", Counter(value=1))
    a.lock("x", cast.LockMode.O)
    with pytest.raises(cast.LockedError, match="locked \\(O\\) by component 'a'"):
        b.overwrite("x", Counter(value=2))
    assert _state(make, "a") != "DISCONNECTED"
    a._cast_close()
    wait_for(lambda: _state(make, "a") == "DISCONNECTED", 10, "a's session to end")
    b.overwrite("x", Counter(value=2))  # its lock went with its session


@rule
def each_component_hears_only_the_decisions_about_its_own_tasks(make: Any) -> None:
    one, two = make(Manager, "one"), make(Manager, "two")
    one.start()
    two.start()
    one.propose_task("first")  # fifo, one at a time: adopted
    two.propose_task("second")  # waits
    wait_for(lambda: len(one.decisions) == 1, 10, "one's decision")
    assert one.decisions == [("adopted", "first", None)]
    assert two.decisions == []  # its task waits; nothing of one's reached it


@rule
def a_listing_shows_entries_without_values_and_counts_as_a_read(make: Any) -> None:
    a, _ = _two(make)
    a.add("x", Pose(label="secret"))
    a.add("y", Counter(value=1))
    before = _reads(make, "a")
    listing = _list(make, "a", "vision", "cast.testing.Pose")
    assert [(e.id, e.type, e.data) for e in listing] == [("x", "cast.testing.Pose", b"")]
    assert _reads(make, "a") == before + 1


def _state(make: Any, component_id: str) -> str:
    """The session state the server records for a component."""
    info = next(i for i in make.system.sessions.components() if i.id == component_id)
    return str(info.state.name)


def _reads(make: Any, component_id: str) -> int:
    """How many reads the server counted of a component."""
    counted = make.system.metrics.snapshot()["components"]
    return int(counted[component_id]["reads"]) if component_id in counted else 0


def _list(make: Any, component_id: str, sa: str, type_name: str) -> list[Any]:
    """The listing a tool gets: over gRPC, Inspection.ListEntries; in process, the rulebook's own call."""
    identity = Identity(component_id, sa)
    if make.mode.startswith("grpc"):
        from cast.client.conversions import entry_from_pb
        from cast.client.credentials import TokenSource
        from cast.client.grpc_transport import GrpcTransport
        from cast.v1 import inspection_pb2

        transport = GrpcTransport(make.endpoint, TokenSource(make.signer.issue(identity)), identity)
        try:
            request = inspection_pb2.ListEntriesRequest(subarchitecture=sa, type=type_name)
            listed = transport._call(transport._directory.inspection.ListEntries, request)
        finally:
            transport.close()
        return [entry_from_pb(e) for e in listed.entries]
    return list(Access(make.system, identity).list_entries(sa, type_name).entries)


@pytest.mark.parametrize("name", sorted(RULES))
def test_rule_holds_in_every_transport(make_component: Any, name: str) -> None:
    RULES[name](make_component)
