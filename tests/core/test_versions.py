"""Versions, expected_version, revisions, the type index and bad input, on the core directly."""

from __future__ import annotations

import pytest

from cast.core.host import BatchOp, MemoryHost
from cast.core.records import EntryRecord, Identity, Limits, Operation
from cast.errors import (
    AlreadyExistsError,
    ConsistencyError,
    InvalidArgumentError,
    NotFoundError,
    ResourceExhaustedError,
)

A = Identity("a1", "vision")
B = Identity("b1", "vision")


@pytest.fixture
def host() -> MemoryHost:
    return MemoryHost(["vision", "language"])


def snapshot(host: MemoryHost) -> tuple[object, ...]:
    """Everything observable about a host's state, for 'nothing changed' checks."""
    return tuple(
        (sa, host.revision(sa), [(r.id, r.type, r.data, r.version, r.author) for r in host.all_entries(sa)])
        for sa in host.subarchitectures
    )


def test_add_gives_version_zero_and_overwrites_add_one(host: MemoryHost) -> None:
    assert host.add(A, "vision", "x", "t.T", b"1").version == 0
    assert host.overwrite(A, "vision", "x", "t.T", b"2").version == 1
    assert host.overwrite(B, "vision", "x", "t.T", b"3").version == 2
    rec = host.get(A, "vision", "x")
    assert (rec.version, rec.data, rec.author) == (2, b"3", "b1")


def test_readd_after_delete_continues_versions(host: MemoryHost) -> None:
    host.add(A, "vision", "x", "t.T", b"1")
    host.overwrite(A, "vision", "x", "t.T", b"2")
    assert host.delete(A, "vision", "x").version == 1
    assert host.add(A, "vision", "x", "t.T", b"3").version == 2
    assert host.get(A, "vision", "x").version == 2


def test_expected_version_mismatch_aborts_and_changes_nothing(host: MemoryHost) -> None:
    host.add(A, "vision", "x", "t.T", b"1")
    host.overwrite(A, "vision", "x", "t.T", b"2")
    before = snapshot(host)
    with pytest.raises(ConsistencyError, match="version 1, expected 0"):
        host.overwrite(B, "vision", "x", "t.T", b"3", expected_version=0)
    with pytest.raises(ConsistencyError):
        host.delete(B, "vision", "x", expected_version=5)
    assert snapshot(host) == before
    assert host.overwrite(B, "vision", "x", "t.T", b"3", expected_version=1).version == 2
    assert host.delete(B, "vision", "x", expected_version=2).version == 2


def test_revisions_number_every_write_without_gaps_per_wm(host: MemoryHost) -> None:
    revs = [host.add(A, "vision", f"e{i}", "t.T", b"").revision for i in range(5)]
    revs.append(host.overwrite(A, "vision", "e0", "t.T", b"x").revision)
    revs.append(host.delete(A, "vision", "e1").revision)
    assert revs == [1, 2, 3, 4, 5, 6, 7]
    other = Identity("l", "language")
    assert host.add(other, "language", "e0", "t.T", b"").revision == 1  # each WM counts its own
    events = host.events_since("vision", 1)
    assert [e.revision for e in events] == list(range(1, 8))
    assert [e.operation for e in events][-2:] == [Operation.OVERWRITE, Operation.DELETE]


def test_failed_writes_do_not_consume_revisions(host: MemoryHost) -> None:
    host.add(A, "vision", "x", "t.T", b"")
    with pytest.raises(AlreadyExistsError):
        host.add(A, "vision", "x", "t.T", b"")
    with pytest.raises(NotFoundError):
        host.overwrite(A, "vision", "missing", "t.T", b"")
    assert host.add(A, "vision", "y", "t.T", b"").revision == 2


def test_type_index_is_newest_first_with_limit(host: MemoryHost) -> None:
    for i in range(5):
        host.add(A, "vision", f"e{i}", "t.T", b"")
    host.add(A, "vision", "other", "t.U", b"")
    host.overwrite(A, "vision", "e1", "t.T", b"touched")  # an overwrite makes it newest
    records, revision = host.get_by_type(A, "vision", "t.T")
    assert [r.id for r in records] == ["e1", "e4", "e3", "e2", "e0"]
    assert revision == 7
    assert [r.id for r in host.get_by_type(A, "vision", "t.T", limit=2)[0]] == ["e1", "e4"]
    host.overwrite(A, "vision", "e4", "t.U", b"")  # a type change moves it between indexes
    assert [r.id for r in host.get_by_type(A, "vision", "t.U")[0]] == ["e4", "other"]
    host.delete(A, "vision", "e1")
    assert [r.id for r in host.get_by_type(A, "vision", "t.T")[0]] == ["e3", "e2", "e0"]
    assert host.get_by_type(A, "vision", "t.Nothing")[0] == []


class _CountingEntries(dict[str, EntryRecord]):
    """A WM's entries that count the reads by id."""

    reads = 0

    def __getitem__(self, key: str) -> EntryRecord:
        self.reads += 1
        return super().__getitem__(key)


def test_a_type_read_with_a_limit_reads_only_that_many_entries(host: MemoryHost) -> None:
    """A limit is kept while reading, not applied to a list of the whole type (which the compiled build once made)."""
    for i in range(1000):
        host.add(A, "vision", f"e{i}", "t.T", b"")
    wm = host._wm("vision")
    wm.entries = counting = _CountingEntries(wm.entries)
    records, _ = host.get_by_type(A, "vision", "t.T", limit=3)
    assert [r.id for r in records] == ["e999", "e998", "e997"]
    assert counting.reads == 3


def test_records_read_are_not_changed_by_later_writes(host: MemoryHost) -> None:
    host.add(A, "vision", "x", "t.T", b"one")
    first = host.get(A, "vision", "x")
    host.overwrite(A, "vision", "x", "t.T", b"two")
    assert (first.data, first.version) == (b"one", 0)


@pytest.mark.parametrize(
    ("entry_id", "type_name", "data", "error", "words"),
    [
        ("", "t.T", b"", InvalidArgumentError, "empty"),
        ("x" * 257, "t.T", b"", InvalidArgumentError, "257 bytes, over the limit of 256"),
        ("bad\nid", "t.T", b"", InvalidArgumentError, "control characters"),
        ("ok", "", b"", InvalidArgumentError, "type is empty"),
        ("ok", "not a type!", b"", InvalidArgumentError, "not a full protobuf message name"),
        ("ok", "t.T", b"x" * 1025, InvalidArgumentError, "1025 bytes, over the limit of 1024"),
    ],
)
def test_bad_input_is_refused_and_changes_nothing(
    entry_id: str, type_name: str, data: bytes, error: type[Exception], words: str
) -> None:
    host = MemoryHost(["vision"], Limits(max_value_bytes=1024))
    host.add(A, "vision", "keep", "t.T", b"")
    before = snapshot(host)
    with pytest.raises(error, match=words):
        host.add(A, "vision", entry_id, type_name, data)
    if entry_id:
        with pytest.raises(error, match=words):
            host.batch(
                A,
                [
                    BatchOp(Operation.ADD, "vision", "fine", "t.T", b""),
                    BatchOp(Operation.ADD, "vision", entry_id, type_name, data),
                ],
            )
    assert snapshot(host) == before


def test_unknown_subarchitecture_is_not_found_and_names_the_known_ones(host: MemoryHost) -> None:
    with pytest.raises(NotFoundError, match="no subarchitecture 'motor'.*known: language, vision"):
        host.get(A, "motor", "x")
    with pytest.raises(NotFoundError, match="motor"):
        host.add(Identity("p", "vision", True), "motor", "x", "t.T", b"")


def test_get_overwrite_delete_of_missing_entry_is_not_found(host: MemoryHost) -> None:
    before = snapshot(host)
    with pytest.raises(NotFoundError, match="no entry 'ghost' in subarchitecture 'vision'"):
        host.get(A, "vision", "ghost")
    with pytest.raises(NotFoundError):
        host.overwrite(A, "vision", "ghost", "t.T", b"")
    with pytest.raises(NotFoundError):
        host.delete(A, "vision", "ghost")
    assert not host.exists(A, "vision", "ghost")
    assert snapshot(host) == before


def test_max_entries_limit_is_a_clear_refusal() -> None:
    host = MemoryHost(["vision"], Limits(max_entries=2))
    host.add(A, "vision", "a", "t.T", b"")
    host.add(A, "vision", "b", "t.T", b"")
    with pytest.raises(ResourceExhaustedError, match="limits.max_entries = 2"):
        host.add(A, "vision", "c", "t.T", b"")
    host.delete(A, "vision", "a")
    host.add(A, "vision", "c", "t.T", b"")


def test_batch_is_applied_in_order_all_or_nothing(host: MemoryHost) -> None:
    results = host.batch(
        A,
        [
            BatchOp(Operation.ADD, "vision", "x", "t.T", b"1"),
            BatchOp(Operation.OVERWRITE, "vision", "x", "t.T", b"2", expected_version=0),
            BatchOp(Operation.DELETE, "vision", "x"),
            BatchOp(Operation.ADD, "vision", "x", "t.T", b"3"),
        ],
    )
    assert [(r.revision, r.version) for r in results] == [(1, 0), (2, 1), (3, 1), (4, 2)]
    before = snapshot(host)
    with pytest.raises(ConsistencyError, match="batch operation 2"):
        host.batch(
            A,
            [
                BatchOp(Operation.ADD, "vision", "y", "t.T", b""),
                BatchOp(Operation.OVERWRITE, "vision", "x", "t.T", b"", expected_version=2),
                BatchOp(Operation.OVERWRITE, "vision", "x", "t.T", b"", expected_version=2),  # now at 3
            ],
        )
    assert snapshot(host) == before
    assert not host.exists(A, "vision", "y")


def test_batch_limit() -> None:
    host = MemoryHost(["vision"], Limits(max_batch_operations=3))
    ops = [BatchOp(Operation.ADD, "vision", f"e{i}", "t.T", b"") for i in range(4)]
    with pytest.raises(InvalidArgumentError, match="4 operations, over the limit of 3"):
        host.batch(A, ops)


def test_a_version_floor_starts_every_entry_there_and_versions_go_on_from_it() -> None:
    floor = 1_700_000_000_000_000
    host = MemoryHost(["vision"], clock=lambda: (floor + 10_000) * 1000, version_floor=floor)
    assert host.add(A, "vision", "x", "t.T", b"1").version == floor
    assert host.overwrite(A, "vision", "x", "t.T", b"2").version == floor + 1
    assert host.delete(A, "vision", "x").version == floor + 1
    assert host.add(A, "vision", "x", "t.T", b"3").version == floor + 2  # re-add continues
    # An entry restored from before the floor (a journal of an earlier run) jumps to it on its next write.
    host.restore("vision", [], {"old": 7}, host.revision("vision"), [])
    assert host.add(A, "vision", "old", "t.T", b"").version == floor


def test_a_floored_version_may_not_outrun_the_clock_in_microseconds() -> None:
    floor = 1_700_000_000_000_000
    now_us = floor + 2
    host = MemoryHost(["vision"], clock=lambda: now_us * 1000, version_floor=floor)
    host.add(A, "vision", "x", "t.T", b"")
    host.overwrite(A, "vision", "x", "t.T", b"")
    host.overwrite(A, "vision", "x", "t.T", b"")  # version floor + 2 == now
    before = snapshot(host)
    with pytest.raises(ResourceExhaustedError, match="past the server's clock"):
        host.overwrite(A, "vision", "x", "t.T", b"")
    with pytest.raises(ResourceExhaustedError, match="batch operation 1: .*past the server's clock"):
        host.batch(A, [BatchOp(Operation.ADD, "vision", "y", "t.T", b""),
                       BatchOp(Operation.OVERWRITE, "vision", "x", "t.T", b"")])
    assert snapshot(host) == before


def test_a_runaway_writer_is_refused_at_the_wm_bound_and_others_go_on() -> None:
    host = MemoryHost(["vision", "language"], Limits(max_total_bytes=10_000))
    big = b"x" * 1000
    for i in range(9):
        host.add(A, "vision", f"a{i}", "t.T", big)
    before = snapshot(host)
    with pytest.raises(ResourceExhaustedError) as err:
        host.add(A, "vision", "a9", "t.T", big)
    message = err.value.message
    assert "limits.max_total_bytes" in message and "'a1' 9,018 bytes in 9 entries" in message, message
    with pytest.raises(ResourceExhaustedError, match="max_total_bytes"):
        host.batch(B, [BatchOp(Operation.DELETE, "vision", "a0"),
                       BatchOp(Operation.ADD, "vision", "b", "t.T", big * 2)])
    assert snapshot(host) == before
    host.add(B, "vision", "small", "t.T", b"ok")  # room left for small writes
    host.add(Identity("l1", "language"), "language", "elsewhere", "t.T", big)  # another WM has its own bound
    host.overwrite(A, "vision", "a0", "t.T", b"")  # shrinking always passes
    host.batch(B, [BatchOp(Operation.DELETE, "vision", "a1"), BatchOp(Operation.ADD, "vision", "b", "t.T", big)])
    assert host.usage("vision")["b1"] == (2, 1000 + 1 + 2 + 5)
    assert host.total_bytes("vision") == sum(b for _, b in host.usage("vision").values())


def test_component_quotas_count_entries_and_bytes_over_every_wm() -> None:
    from cast.core.records import Quota

    boss = Identity("boss", "vision", privileged=True)
    host = MemoryHost(["vision", "language"], quotas={"boss": Quota(entries=3, bytes=250)})
    host.add(boss, "vision", "x", "t.T", b"v" * 100)
    host.add(boss, "language", "y", "t.T", b"v" * 100)
    with pytest.raises(ResourceExhaustedError, match=r"holds 2 entries .*components.boss.quota") as err:
        host.add(boss, "vision", "z", "t.T", b"v" * 100)
    assert "'boss' 202 bytes in 2 entries" in err.value.message, err.value.message
    host.add(boss, "vision", "z", "t.T", b"v" * 10)  # fits in bytes
    with pytest.raises(ResourceExhaustedError, match="entries 3"):
        host.add(boss, "vision", "w", "t.T", b"")
    host.add(B, "vision", "b", "t.T", b"v" * 500)  # others are not bound by boss's quota
    host.overwrite(boss, "vision", "x", "t.T", b"")  # shrinking passes
    # Overwriting another's entry moves it to the writer, so it counts against the writer's quota.
    with pytest.raises(ResourceExhaustedError, match="components.boss.quota"):
        host.overwrite(boss, "vision", "b", "t.T", b"")
    assert host.usage()["boss"] == (3, 1 + 101 + 11)


def test_a_type_read_without_a_type_names_the_type_field(host: MemoryHost) -> None:
    with pytest.raises(InvalidArgumentError, match="GetByType's type field"):
        host.get_by_type(A, "vision", "")
