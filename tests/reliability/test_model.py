"""Property tests: the WM core against a small reference model.

Random sequences of add / overwrite / delete (with and without expected
versions) / try_lock / unlock / get by several components (two in one SA, one
privileged elsewhere) over several SAs and ids. After every step, the result or
the refusal, every entry's version, and every WM's revision agree with the model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hypothesis import given, settings
from hypothesis import strategies as st

from cast.core.host import MemoryHost
from cast.core.records import Identity, LockMode
from cast.errors import (
    AlreadyExistsError,
    CastError,
    ConsistencyError,
    LockedError,
    NotFoundError,
    PermissionDeniedError,
)
from tests.reliability.figures import soak

SAS = ("vision", "language")
IDS = ("x", "y", "z")
WHO = {
    "a": Identity("a", "vision"),
    "b": Identity("b", "vision"),
    "p": Identity("p", "language", privileged=True),
}


@dataclass
class Model:
    """What docs/design.md section 4 says the state is."""

    entries: dict[tuple[str, str], tuple[int, bytes]] = field(default_factory=dict)  # -> (version, data)
    last: dict[tuple[str, str], int] = field(default_factory=dict)  # deleted -> last version
    revision: dict[str, int] = field(default_factory=lambda: dict.fromkeys(SAS, 0))
    locks: dict[tuple[str, str], list[object]] = field(default_factory=dict)  # -> [holder, mode, depth]

    def write(self, who: Identity, op: str, sa: str, eid: str, data: bytes, expected: int | None) -> object:
        key = (sa, eid)
        if sa != who.subarchitecture and not who.privileged:
            return PermissionDeniedError
        current = self.entries.get(key)
        lock = self.locks.get(key)
        if op == "add":
            if current is not None:
                return AlreadyExistsError
            version = self.last.pop(key) + 1 if key in self.last else 0
            self.entries[key] = (version, data)
        else:
            if current is None:
                return NotFoundError
            if lock is not None and lock[0] != who.component_id and (op == "overwrite" or lock[1] != LockMode.O):
                return LockedError
            if expected is not None and expected != current[0]:
                return ConsistencyError
            if op == "overwrite":
                version = current[0] + 1
                self.entries[key] = (version, data)
            else:
                version = current[0]
                del self.entries[key]
                self.last[key] = version
                self.locks.pop(key, None)
        self.revision[sa] += 1
        return (self.revision[sa], version)

    def try_lock(self, who: Identity, sa: str, eid: str, mode: LockMode) -> object:
        key = (sa, eid)
        if key not in self.entries:
            return NotFoundError
        lock = self.locks.get(key)
        if lock is None:
            self.locks[key] = [who.component_id, mode, 1]
            return 1
        if lock[0] != who.component_id:
            return LockedError
        lock[1] = max(lock[1], mode)  # type: ignore[call-overload]
        lock[2] += 1  # type: ignore[operator]
        return lock[2]

    def unlock(self, who: Identity, sa: str, eid: str) -> object:
        key = (sa, eid)
        if key not in self.entries:
            return NotFoundError
        lock = self.locks.get(key)
        if lock is None or lock[0] != who.component_id:
            return LockedError
        lock[2] -= 1  # type: ignore[operator]
        if lock[2] == 0:
            del self.locks[key]
            return 0
        return lock[2]

    def get(self, who: Identity, sa: str, eid: str) -> object:
        key = (sa, eid)
        if key not in self.entries:
            return NotFoundError
        lock = self.locks.get(key)
        if lock is not None and lock[1] == LockMode.ODR and lock[0] != who.component_id:
            return LockedError
        return self.entries[key]


ops = st.tuples(
    st.sampled_from(["add", "overwrite", "delete", "lock", "unlock", "get"]),
    st.sampled_from(sorted(WHO)),
    st.sampled_from(SAS),
    st.sampled_from(IDS),
    st.binary(max_size=4),
    st.one_of(st.none(), st.integers(min_value=0, max_value=3)),
    st.sampled_from([LockMode.O, LockMode.OD, LockMode.ODR]),
)


def _apply(
    host: MemoryHost, op: str, who: Identity, sa: str, eid: str, data: bytes, expected: int | None, mode: LockMode
) -> object:
    if op == "add":
        return tuple(host.add(who, sa, eid, "t.T", data))
    if op == "overwrite":
        return tuple(host.overwrite(who, sa, eid, "t.T", data, expected))
    if op == "delete":
        return tuple(host.delete(who, sa, eid, expected))
    if op == "lock":
        return host.try_lock(who, sa, eid, mode)
    if op == "unlock":
        return host.unlock(who, sa, eid)
    record = host.get(who, sa, eid)
    return (record.version, record.data)


def _outcome(fn: object, *args: object) -> object:
    try:
        return fn(*args)  # type: ignore[operator]
    except CastError as exc:
        return type(exc)


@settings(max_examples=2000 if soak() else 150)
@given(st.lists(ops, max_size=80))
def test_core_agrees_with_the_reference_model(steps: list[tuple[object, ...]]) -> None:
    host = MemoryHost(SAS)
    model = Model()
    for op, name, sa, eid, data, expected, mode in steps:
        who = WHO[name]  # type: ignore[index]
        got = _outcome(_apply, host, op, who, sa, eid, data, expected, mode)
        if op in ("add", "overwrite", "delete"):
            payload = data if op != "delete" else b""
            want = model.write(who, op, sa, eid, payload, expected if op != "add" else None)  # type: ignore[arg-type]
        elif op == "lock":
            want = model.try_lock(who, sa, eid, mode)  # type: ignore[arg-type]
        elif op == "unlock":
            want = model.unlock(who, sa, eid)  # type: ignore[arg-type]
        else:
            want = model.get(who, sa, eid)  # type: ignore[arg-type]
        assert got == want, (op, name, sa, eid, expected, mode)
        for s in SAS:
            assert host.revision(s) == model.revision[s]
            assert {r.id: (r.version, r.data) for r in host.all_entries(s)} == {
                i: v for (ms, i), v in model.entries.items() if ms == s
            }
        for (s, i), lock in model.locks.items():
            assert host.lock_holder(s, i) == (lock[0], lock[1], lock[2])
