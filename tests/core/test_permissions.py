"""Permissions: own SA or privileged; reads are open."""

from __future__ import annotations

import pytest

from cast.core.host import BatchOp, MemoryHost
from cast.core.records import Identity, Operation
from cast.errors import PermissionDeniedError

VISION = Identity("seg", "vision")
LANG = Identity("parser", "language")
BOSS = Identity("coordinator", "coordination", privileged=True)


@pytest.fixture
def host() -> MemoryHost:
    h = MemoryHost(["vision", "language", "coordination"])
    h.add(VISION, "vision", "roi", "t.T", b"v")
    return h


def test_unprivileged_cross_sa_writes_are_refused_naming_component_and_sas(host: MemoryHost) -> None:
    before = host.revisions()
    with pytest.raises(PermissionDeniedError) as info:
        host.add(LANG, "vision", "mine", "t.T", b"")
    assert "component 'parser' (SA 'language')" in info.value.message
    assert "subarchitecture 'vision'" in info.value.message
    with pytest.raises(PermissionDeniedError):
        host.overwrite(LANG, "vision", "roi", "t.T", b"")
    with pytest.raises(PermissionDeniedError):
        host.delete(LANG, "vision", "roi")
    with pytest.raises(PermissionDeniedError):
        host.batch(
            LANG,
            [BatchOp(Operation.ADD, "language", "ok", "t.T", b""), BatchOp(Operation.ADD, "vision", "no", "t.T", b"")],
        )
    assert host.revisions() == before


def test_privileged_component_writes_every_sa(host: MemoryHost) -> None:
    host.add(BOSS, "vision", "goal", "t.T", b"")
    host.overwrite(BOSS, "vision", "roi", "t.T", b"changed")
    host.add(BOSS, "language", "goal", "t.T", b"")
    ev = host.events_since("vision", 2)[0]
    assert (ev.source_component, ev.source_subarchitecture, ev.subarchitecture) == (
        "coordinator",
        "coordination",
        "vision",
    )


def test_reads_are_open_to_every_component(host: MemoryHost) -> None:
    assert host.get(LANG, "vision", "roi").data == b"v"
    assert host.exists(LANG, "vision", "roi")
    assert [r.id for r in host.get_by_type(LANG, "vision", "t.T")[0]] == ["roi"]
