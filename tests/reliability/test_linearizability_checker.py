"""The linearizability checker alone (no server).

Hand-made histories (the bug report's among them); random valid histories, which must pass, each with one op
changed so that it cannot (seeds printed); small random histories compared with a brute-force search over every
order (and every choice of which unknown-outcome ops took effect); large histories, which must take seconds.
"""

from __future__ import annotations

import heapq
import itertools
import json
import random
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import pytest

from tests.reliability.linearizability import CheckResult, Op, check, dump_history, increment, load_history

INIT: dict[str, tuple[str, int] | None] = {"k": ("a", 0)}
Initial = Mapping[str, tuple[str, int] | None]


def rd(client: str, call: float, ret: float | None, value: str | None = None, version: int | None = None,
       key: str = "k") -> Op:
    """A read: ok with (value, version), not_found when value is None, unknown when ret is None."""
    result = "unknown" if ret is None else ("not_found" if value is None else "ok")
    return Op(client, key, "read", None, None, call, ret, result, value, version)


def wr(client: str, call: float, ret: float | None, value: str, version: int | None = None, key: str = "k") -> Op:
    """A write: ok with the new version, not_found when version is None, unknown when ret is None."""
    result = "unknown" if ret is None else ("not_found" if version is None else "ok")
    return Op(client, key, "write", value, None, call, ret, result, None, version)


def cas(client: str, call: float, ret: float | None, expected: int, value: str, version: int | None = None,
        result: str = "ok", key: str = "k") -> Op:
    """A cas: ``result`` ok (new version) or conflict (current version); unknown when ret is None."""
    if ret is None:
        result = "unknown"
    return Op(client, key, "cas", value, expected, call, ret, result, None, version)


def linearizable(ops: list[Op], initial: Initial = INIT, next_version: Callable[[int], int] = increment) -> CheckResult:
    result = check(ops, initial, next_version)
    assert result.ok is True, result.report()
    return result


def violation(ops: list[Op], initial: Initial = INIT, next_version: Callable[[int], int] = increment) -> CheckResult:
    result = check(ops, initial, next_version)
    assert result.ok is False, result.report()
    return result


# -- hand-made linearizable histories ------------------------------------------------------------------------------


def test_sequential() -> None:
    linearizable([
        rd("A", 1, 2, "a", 0), wr("A", 3, 4, "x", 1), rd("B", 5, 6, "x", 1),
        cas("B", 7, 8, 1, "y", 2), cas("A", 9, 10, 1, "z", 2, "conflict"), rd("A", 11, 12, "y", 2),
    ])


@pytest.mark.parametrize("first", ["x", "y"])
def test_overlapping_writes_in_either_order(first: str) -> None:
    second = "y" if first == "x" else "x"
    versions = {first: 1, second: 2}
    linearizable([wr("A", 1, 3, "x", versions["x"]), wr("B", 2, 4, "y", versions["y"]), rd("C", 5, 6, second, 2)])


def test_overlapping_writes_then_read_of_the_first_is_a_violation() -> None:
    violation([wr("A", 1, 3, "x", 1), wr("B", 2, 4, "y", 2), rd("C", 5, 6, "x", 1)])


@pytest.mark.parametrize("seen", [("a", 0), ("x", 1)])
def test_concurrent_read_sees_old_or_new(seen: tuple[str, int]) -> None:
    linearizable([wr("W", 1, 3, "x", 1), rd("R", 2, 4, *seen), rd("R", 5, 6, "x", 1)])


def test_cas_conflict_reports_the_current_version() -> None:
    linearizable([wr("W", 1, 2, "x", 1), cas("C", 3, 4, 0, "c", 1, "conflict"), cas("C", 5, 6, 1, "c", 2)])


def test_unknown_write_that_took_effect() -> None:
    linearizable([wr("W", 1, None, "x"), rd("R", 2, 3, "x", 1), wr("Y", 4, 5, "y", 2)])


def test_unknown_write_that_did_not_take_effect() -> None:
    linearizable([wr("W", 1, None, "x"), rd("R", 2, 3, "a", 0), wr("Y", 4, 5, "y", 1), rd("R", 6, 7, "y", 1)])


def test_unknown_write_taking_effect_long_after_its_call() -> None:
    # The client gave up on it, but it was applied after a later write returned.
    linearizable([wr("W", 1, None, "x"), wr("Y", 2, 3, "y", 1), rd("R", 4, 5, "x", 2)])


def test_unknown_cas_applies_only_if_its_version_matches() -> None:
    linearizable([cas("C", 1, None, 0, "z"), rd("R", 2, 3, "z", 1)])
    violation([cas("C", 1, None, 5, "z"), rd("R", 2, 3, "z", 1)])


def test_a_value_read_pins_where_its_only_unknown_writer_took_effect() -> None:
    violation([wr("W", 1, None, "x"), rd("R", 2, 3, "x", 1), rd("R", 4, 5, "x", 2)])
    violation([cas("C", 1, None, 0, "z"), wr("W", 2, 3, "w", 1), rd("R", 4, 5, "z", 2)])
    linearizable([cas("C", 1, None, 1, "z"), wr("W", 2, 3, "w", 1), rd("R", 4, 5, "z", 2)])


def test_unknown_writes_of_the_same_value() -> None:
    two = [wr("W", 1, None, "x"), wr("V", 1.5, None, "x"), rd("R", 2, 3, "x", 1), rd("R", 4, 5, "x", 2)]
    linearizable(two)
    violation([two[0], *two[2:]])
    linearizable([*two[:2], wr("Y", 2, 3, "y", 1), rd("R", 4, 5, "x", 3)])


def test_unknown_reads_are_ignored() -> None:
    linearizable([rd("R", 1, None), wr("W", 2, 3, "x", 1)])


def test_absent_key() -> None:
    linearizable([rd("A", 1, 2), wr("B", 1.5, 3, "x"), cas("C", 2, 4, 0, "y", result="not_found"),
                  wr("D", 5, None, "z"), rd("A", 6, 7)], {"k": None})
    violation([rd("A", 1, 2), wr("B", 3, 4, "x", 1)], {"k": None})
    violation([rd("A", 1, 2)])


def test_equal_times_order_the_ops() -> None:
    # A return at the very instant of another op's call precedes that call.
    linearizable([wr("W", 1, 2, "x", 1), rd("R", 2, 3, "x", 1)])
    violation([wr("W", 1, 2, "x", 1), rd("R", 2, 3, "a", 0)])
    # A zero-duration op is still well formed.
    linearizable([wr("W", 1, 1, "x", 1), rd("R", 1, 1, "x", 1)])


def test_next_version_is_a_parameter() -> None:
    history = [wr("W", 1, 2, "x", 10), cas("C", 3, 4, 10, "y", 20), cas("C", 5, 6, 10, "z", 20, "conflict")]
    linearizable(history, next_version=lambda n: n + 10)
    violation(history)
    with pytest.raises(ValueError, match="does not increase"):
        check(history, INIT, next_version=lambda n: n)


def test_keys_are_checked_separately() -> None:
    initial: dict[str, tuple[str, int] | None] = {"p": ("a", 0), "q": ("a", 0), "idle": None}
    result = check([
        wr("A", 1, 2, "x", 1, key="p"), rd("B", 3, 4, "a", 0, key="q"),  # q did not see p's write: fine
        wr("A", 5, 6, "y", 1, key="q"), rd("B", 7, 8, "a", 0, key="q"),  # stale read on q
    ], initial)
    assert result.ok is False
    assert [(k.key, k.ok, k.ops) for k in result.keys] == [("idle", True, 0), ("p", True, 1), ("q", False, 3)]


# -- hand-made violations ------------------------------------------------------------------------------------------


def test_stale_read_after_a_write_returned() -> None:
    result = violation([wr("W", 1, 2, "x", 1), rd("R", 3, 4, "a", 0)])
    assert "client R" in result.keys[0].explanation


def test_read_of_a_value_never_written() -> None:
    violation([wr("W", 1, 2, "x", 1), rd("R", 1.5, 4, "zzz", 1)])


def test_two_writes_reporting_the_same_version() -> None:
    violation([wr("A", 1, 3, "x", 1), wr("B", 2, 4, "y", 1)])


@pytest.mark.parametrize("reported", [0, 2, 7])
def test_cas_conflict_at_a_version_the_entry_did_not_have(reported: int) -> None:
    violation([wr("W", 1, 2, "x", 1), cas("C", 3, 4, 5, "c", reported, "conflict"), wr("W", 5, 6, "y", 2)])


def test_cas_conflict_at_its_own_expected_version() -> None:
    violation([cas("C", 1, 2, 0, "c", 0, "conflict")])


def bug_report_history() -> list[Op]:
    return [
        wr("W", 1.0, None, "b"),  # server killed: no answer
        rd("R", 1.1, 1.2, "b", 1),  # ... but R saw it
        cas("C", 1.15, 1.25, 0, "c", 1, "conflict"),  # ... and so did C's refusal
        rd("X", 3.0, 3.1, "a", 0),  # server restarted: the write is gone
        wr("Y", 3.2, 3.3, "d", 1),
        cas("R", 3.4, 3.5, 1, "e", 2),
    ]


def test_bug_report_scenario() -> None:
    result = violation(bug_report_history())
    explanation = result.keys[0].explanation
    print(explanation)
    # It gets stuck at X's read, after W's write (taken as applied) and the two ops that observed it.
    assert "longest linearizable prefix: 2 of 5" in explanation
    assert "[3.000000 .. 3.100000] client X: read() -> ok ('a', 0); from that state the model gives: ok ('b', 1)" \
        in explanation
    assert "state after it: ('b', 1)" in explanation
    # Without the reads of the lost write, it would be fine: the write may have had no effect.
    linearizable([op for op in bug_report_history() if op.client not in ("R", "C")])


def test_budget_exceeded_is_inconclusive_never_ok() -> None:
    result = check(bug_report_history(), INIT, max_steps=3)
    assert result.ok is None and result.keys[0].ok is None
    assert result.keys[0].explanation.startswith("inconclusive")
    ops, initial = generate(random.Random(1), 5000)
    assert check(ops, initial, timeout=0.0).ok is None


def test_malformed_records_are_refused() -> None:
    with pytest.raises(ValueError, match="ret must be None"):
        check([Op("A", "k", "write", "x", None, 1, None, "ok", None, 1)], INIT)
    with pytest.raises(ValueError, match="conflict is for cas only"):
        check([Op("A", "k", "write", "x", None, 1, 2, "conflict", None, 1)], INIT)
    with pytest.raises(ValueError, match="no initial state"):
        check([rd("A", 1, 2, key="other")], INIT)


def test_load_history_round_trip(tmp_path: Path) -> None:
    ops, _ = generate(random.Random(7), 300, keys=("k1", "k2"), n_unknown=5)
    ops.append(rd("R", 0.1, None, key="k1"))
    path = tmp_path / "history.jsonl"
    dump_history(ops, path)
    assert load_history(path) == ops
    first = json.loads(path.read_text().splitlines()[0])
    assert set(first) == {"client", "key", "kind", "value", "expected", "call", "ret", "result", "out_value",
                          "out_version"}
    # Optional fields may be left out; blank lines are skipped.
    path.write_text('\n{"client": "A", "key": "k", "kind": "read", "call": 1, "ret": 2, "result": "not_found"}\n')
    assert load_history(path) == [rd("A", 1.0, 2.0)]


# -- random histories ----------------------------------------------------------------------------------------------


@dataclass
class Planned:
    index: int
    client: str
    key: str
    kind: str
    call: float
    ret: float
    lin: float  # linearization point (for an unknown op: when it took effect, if it did)
    unknown: bool = False
    applied: bool = True


def generate(rng: random.Random, n_ops: int, clients: int = 4, keys: tuple[str, ...] = ("k",), n_unknown: int = 0,
             absent: tuple[str, ...] = (), late: float = 1e-2, alphabet: tuple[str, ...] = (),
             ) -> tuple[list[Op], dict[str, tuple[str, int] | None]]:
    """A linearizable history: clients issue ops back to back; results follow the model in linearization order.

    An unknown-outcome op that took effect did so up to ``late`` seconds after its call. Values written are
    unique, or drawn from ``alphabet`` if given.
    """
    initial = {key: None if key in absent else (f"init-{key}", 0) for key in keys}
    ready = [(rng.uniform(0, 1e-3), f"c{c}") for c in range(clients)]
    plan = []
    for index in range(n_ops):
        t, client = heapq.heappop(ready)
        call = t + rng.uniform(0, 3e-4)
        ret = call + rng.uniform(5e-5, 2e-3)
        kind = rng.choices(["read", "write", "cas"], weights=[4, 3, 3])[0]
        plan.append(Planned(index, client, rng.choice(keys), kind, call, ret, rng.uniform(call, ret)))
        heapq.heappush(ready, (ret, client))
    writers = [p for p in plan if p.kind != "read"]
    for p in rng.sample(writers, min(n_unknown, len(writers))):
        # No answer; it took effect (maybe well after the client gave up on it) or not.
        p.unknown, p.applied, p.lin = True, rng.random() < 0.5, p.call + rng.uniform(0, late)
    state = dict(initial)
    ops: list[Op | None] = [None] * n_ops
    for p in sorted(plan, key=lambda p: (p.lin, p.index)):
        s = state[p.key]
        value = rng.choice(alphabet) if alphabet else f"{p.client}#{p.index}"
        expected = rng.choice([s[1], s[1], s[1] - 1, s[1] + 1]) if s is not None else 0
        if p.kind == "read":
            op = rd(p.client, p.call, p.ret, s[0], s[1], key=p.key) if s else rd(p.client, p.call, p.ret, key=p.key)
        elif s is None:
            op = (wr(p.client, p.call, p.ret, value, key=p.key) if p.kind == "write"
                  else cas(p.client, p.call, p.ret, expected, value, result="not_found", key=p.key))
        elif p.kind == "cas" and expected != s[1]:
            op = cas(p.client, p.call, p.ret, expected, value, s[1], "conflict", key=p.key)
        else:
            if p.applied:
                state[p.key] = (value, s[1] + 1)
            op = (wr(p.client, p.call, p.ret, value, s[1] + 1, key=p.key) if p.kind == "write"
                  else cas(p.client, p.call, p.ret, expected, value, s[1] + 1, key=p.key))
        if p.unknown:
            op = replace(op, ret=None, result="unknown", out_value=None, out_version=None)
        ops[p.index] = op
    return [op for op in ops if op is not None], initial


def corrupt(rng: random.Random, ops: list[Op], initial: Mapping[str, tuple[str, int] | None]) -> tuple[int, Op, str]:
    """Change one known op so that no linearization can exist; returns (index, new op, what was done).

    Each corruption contradicts the fact that versions only grow: nothing is ever at a version again after a
    later one, and an op that starts after another returned is linearized after it.
    """
    known = [i for i, op in enumerate(ops) if op.result != "unknown"]
    reads = [i for i in known if ops[i].kind == "read" and ops[i].result == "ok"]
    writes = [i for i in known if ops[i].kind != "read" and ops[i].result == "ok"]
    conflicts = [i for i in known if ops[i].result == "conflict"]

    def after_a_write(i: int) -> int | None:
        done = [w for w in writes if ops[w].key == ops[i].key and (ops[w].ret or 0) < ops[i].call]
        return rng.choice(done) if done else None

    choices = ["never written", "same version", "stale read", "stale conflict", "conflict at unreached version"]
    rng.shuffle(choices)
    for what in choices:
        if what == "never written" and reads:
            i = rng.choice(reads)
            return i, replace(ops[i], out_value="never-written"), what
        if what == "same version" and len(writes) > 1:
            a = rng.choice(writes)
            others = [b for b in writes if b != a and ops[b].key == ops[a].key]
            if others:
                b = rng.choice(others)
                return b, replace(ops[b], out_version=ops[a].out_version), what
        if what == "stale read" and reads:
            i = rng.choice(reads)
            init = initial[ops[i].key]
            if after_a_write(i) is not None and init is not None:
                return i, replace(ops[i], out_value=init[0], out_version=init[1]), what
        if what == "stale conflict" and conflicts:
            i = rng.choice(conflicts)
            w = after_a_write(i)
            if w is not None:
                return i, replace(ops[i], out_version=(ops[w].out_version or 0) - 1), what
        if what == "conflict at unreached version" and conflicts:
            i = rng.choice(conflicts)
            return i, replace(ops[i], out_version=10**6), what
    raise AssertionError("no corruption applies")


@pytest.mark.parametrize("seed", range(40))
def test_random_history_is_linearizable_and_a_corruption_is_not(seed: int) -> None:
    print(f"seed={seed}")
    rng = random.Random(seed)
    ops, initial = generate(rng, rng.randint(50, 400), clients=rng.randint(2, 5), keys=("k1", "k2", "k3"),
                            n_unknown=rng.randint(0, 8), absent=("k3",) if seed % 4 == 0 else (),
                            late=rng.choice([1e-3, 1e-2, 1.0]))
    result = check(ops, initial)
    assert result.ok is True, f"seed={seed}\n{result.report()}"
    i, bad, what = corrupt(rng, ops, initial)
    broken = check([*ops[:i], bad, *ops[i + 1:]], initial)
    context = f"seed={seed}: {what}: {ops[i].describe()} became {bad.describe()}\n{broken.report()}"
    assert broken.ok is False, context
    # Only the key of the corrupted op is affected.
    assert [k.key for k in broken.keys if not k.ok] == [bad.key], context


@pytest.mark.parametrize("n_unknown", [20, 300])
def test_large_history_is_checked_in_seconds(n_unknown: int) -> None:
    rng = random.Random(2024)
    # Unknown-outcome ops that took effect did so anywhere in the following 5 s (the history lasts about 4 s).
    # (300: a workload that records calls refused while the server is down as unknown too.)
    ops, initial = generate(rng, 15_000, clients=4, n_unknown=n_unknown, late=5.0)
    start = time.monotonic()
    result = check(ops, initial)
    elapsed = time.monotonic() - start
    print(f"15,000 ops, {n_unknown} unknown: {elapsed:.2f} s, {result.keys[0].steps} steps")
    assert result.ok is True, result.report()
    # A stale read near the end: the search has to give up on the whole history.
    late = [i for i, op in enumerate(ops) if op.kind == "read" and op.result == "ok" and op.call > ops[-100].call]
    i = late[0]
    start = time.monotonic()
    broken = check([*ops[:i], replace(ops[i], out_value="init-k", out_version=0), *ops[i + 1:]], initial)
    print(f"with a stale read near the end: {time.monotonic() - start:.2f} s, {broken.keys[0].steps} steps")
    assert broken.ok is False, broken.report()
    assert f"client {ops[i].client}: read() -> ok ('init-k', 0)" in broken.keys[0].explanation


# -- against a brute-force search ----------------------------------------------------------------------------------


def spec(state: tuple[str, int] | None, op: Op) -> tuple[bool, tuple[str, int] | None]:
    """The sequential specification, written out plainly: is ``op``'s record allowed in ``state``, and what next.

    An unknown-outcome op passed here is one taken to have had its effect.
    """
    if state is None:
        return op.result in ("not_found", "unknown"), None
    version = state[1]
    if op.kind == "read":
        return op.result == "ok" and (op.out_value, op.out_version) == state, state
    if op.kind == "cas" and op.expected != version:
        return op.result == "unknown" or (op.result == "conflict" and op.out_version == version), state
    assert op.value is not None
    return op.result == "unknown" or (op.result == "ok" and op.out_version == version + 1), (op.value, version + 1)


def precedes(a: Op, b: Op) -> bool:
    """Real-time order, with the checker's conventions for equal times."""
    return a.ret is not None and (a.ret < b.call or (a.ret == b.call and a.call < a.ret))


def brute_force(ops: list[Op], initial: tuple[str, int] | None) -> bool:
    """Linearizable iff some subset of the unknown-outcome ops, with all the known ones, has a legal order."""
    known = [op for op in ops if op.result != "unknown"]
    unknown = [op for op in ops if op.result == "unknown" and op.kind != "read"]

    def search(state: tuple[str, int] | None, remaining: tuple[Op, ...]) -> bool:
        if not remaining:
            return True
        for i, op in enumerate(remaining):
            rest = remaining[:i] + remaining[i + 1:]
            if not any(precedes(other, op) for other in rest):
                allowed, new = spec(state, op)
                if allowed and search(new, rest):
                    return True
        return False

    return any(search(initial, (*known, *chosen))
               for n in range(len(unknown) + 1) for chosen in itertools.combinations(unknown, n))


def mutate(rng: random.Random, op: Op, values: list[str]) -> Op:
    """A small change to a record that keeps it well formed."""
    if op.result == "unknown":
        return op if op.kind != "cas" else replace(op, expected=(op.expected or 0) + rng.choice([-1, 1]))
    choices = ["version"] if op.out_version is not None else []
    if op.kind == "read" and op.result == "ok":
        choices.append("value")
    if op.kind == "cas" and op.result == "conflict":
        choices.append("expected")
    what = rng.choice(choices) if choices else ""
    if what == "version":
        return replace(op, out_version=(op.out_version or 0) + rng.choice([-1, 1]))
    if what == "value":
        return replace(op, out_value=rng.choice(values))
    if what == "expected":
        return replace(op, expected=(op.expected or 0) + rng.choice([-1, 1]))
    return op


@pytest.mark.parametrize("seed", range(400))
def test_small_histories_agree_with_brute_force(seed: int) -> None:
    print(f"seed={seed}")
    rng = random.Random(seed)
    ops, initial = generate(rng, rng.randint(1, 8), clients=rng.randint(1, 4), n_unknown=rng.randint(0, 3),
                            absent=("k",) if seed % 10 == 0 else (), late=rng.choice([1e-3, 1e-2]),
                            alphabet=("init-k", "x", "y")[:rng.choice([0, 2, 3])])
    # Coarse times make ties (and zero-duration ops); a mutation makes most histories wrong.
    q = rng.choice([2e-4, 5e-4])
    ops = [replace(op, call=round(op.call / q) * q, ret=None if op.ret is None else round(op.ret / q) * q)
           for op in ops]
    if seed % 3:
        i = rng.randrange(len(ops))
        values = ["init-k", *(op.value for op in ops if op.value is not None)]
        ops[i] = mutate(rng, ops[i], values)
    expected = brute_force(ops, initial["k"])
    result = check(ops, initial)
    history = "\n".join(op.describe() for op in sorted(ops, key=lambda op: op.call))
    assert result.ok is expected, f"seed={seed} brute force says {expected}:\n{history}\n{result.report()}"
