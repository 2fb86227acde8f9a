"""The streamed write path across languages, for the C++ and the Java probe against Python and
against each other: pipelined writes keep call order and report refusals on their futures, 1.5 MiB values
go both ways (read and watched), latest delivery conflates for a slow callback whichever language writes,
a probe's high-priority callback runs before its pending low ones, and the named errors of the Write
stream are the unary ones.

One server and one probe per language serve every test of the module (module-scoped fixtures), each test
on entries of its own. The probes' commands: cpp_client/tests/components/probe_streamed.cc and
java_client/src/test/java/cast/itest/Streamed.java, behind tests/interop/probes.py.
"""

from __future__ import annotations

import random
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import wait
from typing import Any

import pytest
from cast_testing_pb2 import Counter
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client.component import Component
from tests.conftest import DEFAULT_CONFIG, ServerHandle, start_server, wait_for
from tests.interop.probes import COUNTER, Driver, address, counter_json, local_type, start

LANGS = ["cpp", "java"]
PIPELINED = 200
TAKEN = 150  # the index of the pipelined add whose id Python took first
BIG = 1536 * 1024  # 1.5 MiB: more than a VGA RGB image (0.9 MiB)
OVERWRITES = 40
SLOW_MS = 150  # the slow callbacks' sleep: many times what 40 pipelined overwrites take
BUSY_MS = 1000  # a callback that keeps the dispatcher busy while the changes of one batch arrive


def pattern(size: int) -> bytes:
    """The probes' big value: byte i = i % 251."""
    return (bytes(range(251)) * (size // 251 + 1))[:size]


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerHandle]:
    """One real server for the module."""
    handle = start_server(tmp_path_factory.mktemp("streamed"), DEFAULT_CONFIG)
    yield handle
    handle.stop()


@pytest.fixture(scope="module")
def probe(system: ServerHandle) -> Iterator[Callable[[str], Driver]]:
    """The probe of a language (component ``<lang>stream`` in vision), started on first use and kept for the
    module; each must then quit cleanly."""
    started: dict[str, Driver] = {}

    def get(lang: str) -> Driver:
        if lang not in started:
            started[lang] = start(lang, system.env(f"{lang}stream", "vision"))
            started[lang].ready()
        return started[lang]

    yield get
    try:
        statuses = {lang: p.quit() for lang, p in started.items()}
        assert all(s == 0 for s in statuses.values()), statuses
    finally:
        for p in started.values():
            p.close()


@pytest.fixture(scope="module")
def py(system: ServerHandle) -> Iterator[Component]:
    """The Python component of the module (``pystream`` in vision)."""
    component = system.connect("pystream", "vision")
    yield component
    component._cast_close()


class Seen:
    """What a Python callback received, in order; optionally slow."""

    def __init__(self, sleep: float = 0.0) -> None:
        self.sleep = sleep
        self.changes: list[cast.WorkingMemoryChange] = []
        self.lock = threading.Lock()

    def __call__(self, change: cast.WorkingMemoryChange) -> None:
        time.sleep(self.sleep)
        with self.lock:
            self.changes.append(change)

    def copy(self) -> list[cast.WorkingMemoryChange]:
        """The changes received so far."""
        with self.lock:
            return list(self.changes)


def assert_conflated(events: list[dict[str, Any]], revisions: list[int]) -> None:
    """A latest watch's events over ``revisions`` (every change made): fewer callbacks than changes, the last
    one the newest, each skipped change counted once and lying between its neighbours."""
    got = [(e["revision"], e["skipped"], e["first_skipped_revision"]) for e in events]
    told = f"(revision, skipped, first skipped) of each callback: {got}; changes: {revisions[0]}..{revisions[-1]}"
    assert 0 < len(events) < len(revisions), told
    assert events[-1]["revision"] == revisions[-1], told
    assert sum(e["skipped"] for e in events) + len(events) == len(revisions), told
    previous = revisions[0] - 1
    for revision, skipped, first in got:
        assert revision in revisions and revision > previous, told
        if skipped:
            # The changes it skipped are exactly those between the previous callback's and its own.
            assert previous < first < revision, told
            assert revisions.index(revision) - revisions.index(first) == skipped, told
        else:
            assert first == 0, told
        previous = revision


def probe_events_until(p: Driver, watch: Any, done: Callable[[list[dict[str, Any]]], bool]) -> list[dict[str, Any]]:
    """The events of a probe's watch once ``done(events)`` holds (polled; 30 s guard against a hang)."""
    box: list[list[dict[str, Any]]] = []

    def ready() -> bool:
        events = p.watch_events(watch)
        box[:] = [events]
        return done(events)

    wait_for(ready, 30, f"the {p.lang} probe's events")
    return box[0]


# ------------------------------------------------------------------ pipelined writes


@pytest.mark.parametrize("lang", LANGS)
def test_pipelined_probe_writes_apply_in_call_order_with_refusals_on_their_futures(
        lang: str, probe: Callable[[str], Driver], py: Component) -> None:
    p, prefix, writer = probe(lang), f"pipe-{lang}", f"{lang}stream"
    seen = Seen()
    handle = py.on_change(cast.source_filter(writer, cast.Operation.ADD), seen)
    py.add(f"{prefix}-{TAKEN}", Counter(writer="pystream", value=-1))

    r = p.ok("add_async", prefix=prefix, n=PIPELINED)
    # Only the taken id is refused, on its own future, by name; the writes after it still apply.
    assert r["errors"] == [{"index": TAKEN, "error": "AlreadyExistsError", "code": "ALREADY_EXISTS"}], r["errors"]
    applied = [(f"{prefix}-{i}", rev) for i, rev in enumerate(r["revisions"]) if i != TAKEN]
    assert r["revisions"][TAKEN] == 0
    revisions = [rev for _, rev in applied]
    assert revisions == sorted(revisions) and len(set(revisions)) == PIPELINED - 1, "applied in call order"
    # Python, watching, sees the same writes in the same order.
    wait_for(lambda: len([c for c in seen.copy() if c.id.startswith(prefix)]) >= PIPELINED - 1, 30, "the adds")
    assert [(c.id, c.revision) for c in seen.copy() if c.id.startswith(prefix)] == applied
    handle.cancel()
    assert py.get(f"{prefix}-7", Counter) == Counter(writer=writer, value=7)
    assert py.get(f"{prefix}-{TAKEN}", Counter).writer == "pystream", "a refused write changes nothing"

    # Pipelined overwrites of one entry: one version after the other, the last value wins.
    v0 = r["versions"][0]
    r = p.ok("overwrite_async", id=f"{prefix}-0", n=20)
    assert r["errors"] == [] and r["versions"] == [v0 + i for i in range(1, 21)], r
    assert py.get(f"{prefix}-0", Counter).value == 20


@pytest.mark.parametrize("lang", LANGS)
def test_stream_refusals_reach_the_probe_by_name(lang: str, probe: Callable[[str], Driver], py: Component) -> None:
    p, entry = probe(lang), f"refused-{lang}"
    v0 = p.ok("add", id=entry, type=COUNTER, value=counter_json("x", 0))["version"]
    err = p.fails("ConsistencyError", "overwrite", id=entry, type=COUNTER, value=counter_json("x", 1),
                  expected_version=v0 + 3)
    assert err["code"] == "ABORTED", err
    guard = py.lock(entry, cast.LockMode.O)
    try:
        err = p.fails("LockedError", "overwrite", id=entry, type=COUNTER, value=counter_json("x", 2))
        assert err["code"] == "FAILED_PRECONDITION" and "pystream" in err["message"], err
        # On a pipelined write's future too, for each of them.
        r = p.ok("overwrite_async", id=entry, n=2)
        assert [e["error"] for e in r["errors"]] == ["LockedError", "LockedError"], r
    finally:
        guard.unlock()
    assert py.get_entry(entry, Counter).version == v0, "refused writes change nothing"
    p.ok("overwrite", id=entry, type=COUNTER, value=counter_json("x", 3), expected_version=v0)


# ------------------------------------------------------------------ large values


@pytest.mark.parametrize("lang", LANGS)
def test_large_values_go_both_ways_and_reach_watchers(lang: str, probe: Callable[[str], Driver],
                                                      py: Component) -> None:
    p = probe(lang)
    from_py, from_probe = f"big-py-{lang}", f"big-{lang}"
    value = random.Random(19).randbytes(BIG)
    watch = p.watch(address(from_py, include_entry=True))
    seen = Seen()
    handle = py.on_change(cast.address_filter(from_probe, include_entry=True), seen)

    py.add(from_py, BytesValue(value=value))
    got = p.ok("big_read", id=from_py)
    assert (got["size"], got["crc32"], got["author"]) == (BIG, zlib.crc32(value), "pystream"), got
    [event] = p.watch_events(watch, 1, 30_000)
    assert (event["size"], event["crc32"], event["id"]) == (BIG, zlib.crc32(value), from_py), event

    expected = pattern(BIG)
    w = p.ok("big_write", id=from_probe, size=BIG)
    assert (w["size"], w["crc32"]) == (BIG, zlib.crc32(expected)), "the probe made the agreed bytes"
    assert py.get(from_probe, BytesValue).value == expected
    wait_for(seen.copy, 30, "Python's event of the probe's big value")
    [change] = seen.copy()
    assert change.revision == w["revision"] and change.entry(BytesValue).value.value == expected
    handle.cancel()


# ------------------------------------------------------------------ latest delivery


@pytest.mark.parametrize("lang", LANGS)
def test_latest_delivery_to_a_slow_probe_callback(lang: str, probe: Callable[[str], Driver], py: Component) -> None:
    p, entry = probe(lang), f"fast-py-{lang}"
    py.add(entry, Counter(writer="pystream", value=0))
    watch = p.watch(address(entry, include_entry=True), delivery="latest", slow_ms=SLOW_MS)
    futures = [py.overwrite_async(entry, Counter(writer="pystream", value=i)) for i in range(1, OVERWRITES + 1)]
    wait(futures, 30)
    revisions = [f.result().revision for f in futures]

    events = probe_events_until(p, watch, lambda ev: bool(ev) and ev[-1]["revision"] == revisions[-1])
    assert events[-1]["value"] == counter_json("pystream", OVERWRITES), "the newest value comes last"
    assert_conflated(events, revisions)


@pytest.mark.parametrize("lang", LANGS)
def test_latest_delivery_to_a_slow_python_callback(lang: str, probe: Callable[[str], Driver], py: Component) -> None:
    p, entry = probe(lang), f"fast-{lang}"
    p.ok("add", id=entry, type=COUNTER, value=counter_json(f"{lang}stream", 0))
    seen = Seen(sleep=SLOW_MS / 1000)
    handle = py.on_change(cast.address_filter(entry, include_entry=True), seen, delivery="latest")
    r = p.ok("overwrite_async", id=entry, n=OVERWRITES)
    assert r["errors"] == [], r

    wait_for(lambda: (c := seen.copy()) and c[-1].revision == r["revisions"][-1], 30, "the newest change")
    handle.cancel()
    changes = seen.copy()
    assert changes[-1].entry(Counter).value.value == OVERWRITES
    assert_conflated([{"revision": c.revision, "skipped": c.skipped, "first_skipped_revision": c.first_skipped_revision}
                      for c in changes], r["revisions"])


@pytest.mark.parametrize("lang", LANGS)
def test_probe_priorities_order_pending_callbacks(lang: str, probe: Callable[[str], Driver], py: Component) -> None:
    p = probe(lang)
    busy, low, high = (f"{name}-{lang}" for name in ("busy", "low", "high"))
    watches = {
        busy: p.watch(address(busy), slow_ms=BUSY_MS),
        low: p.watch(address(low), priority="low"),
        high: p.watch(address(high), priority="high"),
    }
    # One batch: three changes at once. The busy callback holds the probe's dispatcher while the other two
    # wait; then the high-priority one runs first, though the low one's change came first.
    py.batch([("add", entry, Counter(writer="pystream")) for entry in (busy, low, high)])
    seq = {entry: p.watch_events(w, 1, 30_000)[0]["seq"] for entry, w in watches.items()}
    assert seq[high] < seq[low], seq


# ------------------------------------------------------------------ C++ <-> Java


def test_cpp_and_java_pipelined_large_and_latest(probe: Callable[[str], Driver]) -> None:
    c, j = probe("cpp"), probe("java")
    # Java pipelines adds that C++ watches; C++ writes a big value Java reads and watches; C++ overwrites fast
    # an entry Java watches with latest delivery and a slow callback.
    adds = c.watch(local_type(COUNTER))
    big = j.watch(address("big-cj", include_entry=True))
    c.ok("add", id="fast-cj", type=COUNTER, value=counter_json("cppstream", 0))
    fast = j.watch(address("fast-cj", include_entry=True), delivery="latest", slow_ms=SLOW_MS)

    r = j.ok("add_async", prefix="jc", n=100)
    assert r["errors"] == [], r
    c.ok("big_write", id="big-cj", size=BIG)
    w = c.ok("overwrite_async", id="fast-cj", n=OVERWRITES)

    def of_java(ev: list[dict[str, Any]]) -> list[dict[str, Any]]:
        return [e for e in ev if e["id"].startswith("jc-")]

    events = probe_events_until(c, adds, lambda ev: len(of_java(ev)) >= 100)
    assert [(e["id"], e["revision"]) for e in of_java(events)] == [(f"jc-{i}", r["revisions"][i]) for i in range(100)]
    got = j.ok("big_read", id="big-cj")
    assert (got["size"], got["crc32"], got["author"]) == (BIG, zlib.crc32(pattern(BIG)), "cppstream"), got
    [event] = j.watch_events(big, 1, 30_000)
    assert (event["size"], event["crc32"]) == (BIG, zlib.crc32(pattern(BIG))), event
    events = probe_events_until(j, fast, lambda ev: bool(ev) and ev[-1]["revision"] == w["revisions"][-1])
    assert events[-1]["value"] == counter_json("cppstream", OVERWRITES)
    assert_conflated(events, w["revisions"])
