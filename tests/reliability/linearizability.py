"""Linearizability checker for histories of operations on versioned registers.

A port of the Wing-Gong algorithm with Lowe's memoisation (as in Go's porcupine):
call and return events sorted by time in a doubly linked list; a depth-first
search that repeatedly linearizes a *minimal* pending call (no return event
before it) whose step the sequential model allows, lifts its events out of the
list and starts again from the head; backtracking when no candidate is left; and
a cache of (linearized set as a bitset, model state) so that no configuration is
explored twice. Keys are independent, so each is checked alone
(P-compositionality): a history is linearizable iff every key's part is.

Conventions:

* Time: an operation whose ``ret`` equals another's ``call`` precedes it (at
  equal times returns sort before calls), except that a zero-duration operation
  (``ret == call``) has its return after every call at that instant (it cannot
  precede its own call), so it is concurrent with the operations called then.
* Unknown outcome (``result == "unknown"``, ``ret is None``): the operation may
  have taken effect at any instant after its call, or not at all. Its return is
  at +infinity, so it constrains nothing: its call stays out of the list, the
  search may *apply* it in any configuration where its call precedes the first
  pending return, and those never applied had no effect (always allowed).
  Unknown reads are ignored.
* Versions must strictly increase (``next_version(n) > n``, checked): the
  pruning below relies on it.

Additions to WGL, without which unknown-outcome operations (pending for the rest
of the history) make the search exponential:

* Values no read returned cannot be told apart: they are all encoded as one.
* Unknown operations with the same effect are interchangeable once called: only
  the earliest unapplied one of such a class is tried. Unknown writes of unread
  values form the *pool*: they may apply at any version. An unknown cas can only
  apply at its expected version. The only operation that could have written a
  value that was read must have taken effect, producing the version it was read
  at, and may apply only so. Other unknown writes (of values others wrote too)
  may apply at any version; many of them can make the search slow (inconclusive),
  so workloads should write unique values.
* Once the version has passed the only one at which an unknown operation could
  apply, whether it was applied no longer matters. So the cache keys on (known
  operations linearized, state, applied counts of the "other" classes) and keeps
  the fewest pool operations used: a configuration reached with as many or more
  used has fewer possibilities left, and is pruned (the pool is tried last).
* A state whose version exceeds what a pending known operation needs (a read of
  version n needs <= n, a write reporting n needs < n, ...) cannot complete:
  applying an unknown operation into one is pruned.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from tests.reliability.history import KINDS, RESULTS, Op, dump_history, load_history, validate

__all__ = [
    "DEFAULT_MAX_STEPS", "KINDS", "RESULTS", "CheckResult", "KeyResult", "Op", "check", "dump_history", "increment",
    "load_history", "validate",
]

DEFAULT_MAX_STEPS = 10_000_000
"""Search steps allowed per key before the verdict is "inconclusive" (about a second per million)."""

State = tuple[str, int] | None
"""A register's state: ``(value, version)``, or None when the entry does not exist."""


def increment(version: int) -> int:
    """The default version step: ``n -> n + 1``."""
    return version + 1


@dataclass
class KeyResult:
    """The verdict for one key."""

    key: str
    ok: bool | None  # True linearizable, False not, None inconclusive (budget exceeded)
    ops: int
    explanation: str
    steps: int = 0  # search steps spent


@dataclass
class CheckResult:
    """The verdict for a history: False if any key is not linearizable, else None if any is inconclusive."""

    ok: bool | None
    keys: list[KeyResult]

    def report(self) -> str:
        """All keys' verdicts and explanations, as text."""
        return "\n".join(f"key {k.key!r}: ok={k.ok}, {k.ops} ops, {k.steps} steps\n{k.explanation}" for k in self.keys)


def check(
    ops: Iterable[Op],
    initial: Mapping[str, tuple[str, int] | None],
    next_version: Callable[[int], int] = increment,
    max_steps: int = DEFAULT_MAX_STEPS,
    timeout: float | None = None,
) -> CheckResult:
    """Check a history key by key; ``initial`` must give every key's initial state (None: absent).

    ``max_steps`` bounds the search of each key, ``timeout`` (seconds) the whole
    check; a key whose search is cut short is reported inconclusive (ok=None).
    """
    by_key: dict[str, list[Op]] = {key: [] for key in initial}
    for op in ops:
        validate(op)
        if op.key not in by_key:
            raise ValueError(f"no initial state given for key {op.key!r}")
        by_key[op.key].append(op)
    deadline = None if timeout is None else time.monotonic() + timeout
    results = []
    for key in sorted(by_key):
        init = initial[key]
        search = _Search(key, by_key[key], None if init is None else (init[0], init[1]), next_version)
        results.append(search.run(max_steps, deadline))
    verdicts = {r.ok for r in results}
    return CheckResult(False if False in verdicts else None if None in verdicts else True, results)


@dataclass
class _Stuck:
    """A dead end of the search; the deepest one explains a violation."""

    depth: int  # known ops linearized
    tail: list[int]  # the last op ids of the linearized prefix
    state: State  # the real state after the prefix
    window: list[int]  # the minimal pending known calls there
    free: list[int]  # the unknown ops called by then and not applied
    applied: int  # unknown ops applied in the prefix


# Step modes of compiled operations. Known: the step is allowed iff the state
# matches what the record says. Unknown (_U_*): the step *applies* the effect.
_ABSENT, _EXACT, _VERSION, _WRITE, _CAS_OK, _NEVER, _U_WRITE, _U_CAS = range(8)
_INF = float("inf")


class _Search:
    """WGL search over one key's operations. States are encoded as ``version * M + value code`` (None: absent)."""

    def __init__(self, key: str, ops: list[Op], initial: State, next_version: Callable[[int], int]) -> None:
        self.key, self.ops_count, self.initial, self._next = key, len(ops), initial, next_version
        known = sorted((op for op in ops if op.result != "unknown"), key=lambda op: op.call)
        unknown = sorted((op for op in ops if op.result == "unknown" and op.kind != "read"), key=lambda op: op.call)
        self.ops = known + unknown  # op ids: known first, so that their bitset is dense
        self.n_known = len(known)
        # Only values some read returned can be told apart; every other value gets code 0.
        self.seen: dict[str, set[int]] = {}  # value read -> the versions it was read at
        for op in known:
            if op.kind == "read" and op.out_value is not None and op.out_version is not None:
                self.seen.setdefault(op.out_value, set()).add(op.out_version)
        self.codes = {v: i + 1 for i, v in enumerate(sorted(self.seen))}
        self.m = len(self.codes) + 1
        self.writers = Counter(op.value for op in self.ops if op.result in ("ok", "unknown") and op.kind != "read")
        if initial is not None:
            self.writers[initial[0]] += 1
        # Per op: (step mode, the state or version the record names, expected version, code of the value
        # written, the only version an unknown op may produce or None), and the highest version the state
        # may have when the op is linearized.
        self.spec: list[tuple[int, int, int, int, int | None]] = []
        self.bound: list[float] = []
        self.cls: list[int] = []  # class of an unknown op (-1: a known op, or one that can never apply)
        self.rank: list[int] = []  # position in its class
        self.class_ops: list[list[int]] = []
        self.pool = -1  # the class of unknown writes of values no read returned
        self.free: list[int] = []  # classes of other unknown writes that may apply at any version
        self.at_version: dict[int, list[int]] = {}  # classes that can only apply at that version (cas)
        self.to_version: dict[int, list[int]] = {}  # classes that can only apply so as to produce that version
        keys: dict[tuple[int, ...], int] = {}
        for i, op in enumerate(self.ops):
            self._compile(i, op, keys)
        self._build_list()

    def nv(self, version: int) -> int:
        """The next version, checked to increase (the pruning relies on it)."""
        new = self._next(version)
        if new <= version:
            raise ValueError(f"next_version({version}) = {new} does not increase")
        return new

    def encode(self, state: State) -> int | None:
        """The search's encoding of a state."""
        return None if state is None else state[1] * self.m + self.codes.get(state[0], 0)

    def _compile(self, i: int, op: Op, keys: dict[tuple[int, ...], int]) -> None:
        mode, arg, bound, target = _NEVER, 0, _INF, None
        cls: tuple[int, ...] | None = None
        expected = op.expected if op.expected is not None else 0
        ver = op.out_version if op.out_version is not None else 0
        code = 0 if op.value is None else self.codes.get(op.value, 0)
        if op.result == "unknown":
            mode = _U_CAS if op.kind == "cas" else _U_WRITE
            cls = (mode, code, expected if mode == _U_CAS else 0)
            if code and self.writers[op.value] == 1:
                # The only op that could have written a value that was read took effect, producing the
                # version it was read with; if reads disagree on that version, it can never apply.
                versions = self.seen[op.value or ""]
                target = min(versions)
                cls = (-1, i) if len(versions) == 1 else None
        elif op.result == "not_found":
            mode = _ABSENT
        elif op.kind == "read":
            mode, arg, bound = _EXACT, ver * self.m + self.codes.get(op.out_value or "", 0), ver
        elif op.result == "conflict":
            if ver != expected:  # a conflict at the expected version contradicts itself: never allowed
                mode, arg, bound = _VERSION, ver, ver
        elif op.kind == "write":
            mode, arg, bound = _WRITE, ver, ver - 1
        elif self.nv(expected) == ver:
            mode, arg, bound = _CAS_OK, ver, expected
        self.spec.append((mode, arg, expected, code, target))
        self.bound.append(bound)
        k = -1 if cls is None else keys.setdefault(cls, len(keys))
        if k == len(self.class_ops):
            self.class_ops.append([])
            if mode == _U_CAS:
                self.at_version.setdefault(expected, []).append(k)
            elif target is not None:
                self.to_version.setdefault(target, []).append(k)
            elif code:
                self.free.append(k)
            else:
                self.pool = k
        self.cls.append(k)
        self.rank.append(len(self.class_ops[k]) if k >= 0 else -1)
        if k >= 0:
            self.class_ops[k].append(i)

    def _build_list(self) -> None:
        """Sort the events and link those of known ops; the head sentinel is ``len(events)``."""
        events = []
        for i, op in enumerate(self.ops):
            events.append((op.call, 1, i, 0))
            if op.ret is not None:
                # At equal times returns sort before calls (rank 0 < 1), except a zero-duration op's own
                # return, which must follow its call: it goes after every call at that instant (rank 2).
                events.append((op.ret, 0 if op.ret > op.call else 2, i, 1))
        events.sort()
        n = self.head = len(events)
        self.ent_op = [e[2] for e in events]
        self.ent_ret = [e[3] == 1 for e in events]
        self.match = [-1] * n
        self.call_pos = [0] * len(self.ops)
        for e, (_, _, i, is_ret) in enumerate(events):
            if is_ret:
                self.match[self.call_pos[i]] = e
            else:
                self.call_pos[i] = e
        # Unknown ops' calls stay out of the list: the search looks them up by class (see run).
        linked = [e for e in range(n) if self.ent_op[e] < self.n_known]
        self.nxt, self.prv = [-1] * (n + 1), [-1] * (n + 1)
        for a, b in zip([n, *linked], [*linked, -1], strict=True):
            self.nxt[a] = b
            if b != -1:
                self.prv[b] = a

    def step(self, i: int, s: int | None) -> tuple[bool, int | None]:
        """Whether op ``i`` may be linearized in state ``s``, and the state after it."""
        mode, arg, expected, code, target = self.spec[i]
        if mode == _EXACT:
            return s == arg, s
        if s is None:
            return mode == _ABSENT, s
        if mode in (_ABSENT, _NEVER):
            return False, s
        ver = s // self.m
        if mode == _VERSION:
            return ver == arg, s
        if mode == _WRITE:
            return self.nv(ver) == arg, arg * self.m + code
        if mode == _CAS_OK:
            return ver == expected, arg * self.m + code
        if mode == _U_CAS and ver != expected:
            return False, s
        new = self.nv(ver)
        return target is None or new == target, new * self.m + code

    def candidates(self, s: int | None) -> list[int]:
        """The classes of unknown ops that might apply in state ``s``; the pool last (see run)."""
        if s is None:
            return []
        v = s // self.m
        found = [*self.at_version.get(v, ()), *(self.to_version.get(self.nv(v), ()) if self.to_version else ())]
        return [*found, *self.free, *([self.pool] if self.pool >= 0 else [])]

    def window(self) -> list[int]:
        """The minimal pending known calls (op ids, in list order)."""
        ids, e = [], self.nxt[self.head]
        while e != -1 and not self.ent_ret[e]:
            ids.append(self.ent_op[e])
            e = self.nxt[e]
        return ids

    def version_bound(self) -> float:
        """The highest version the state may have now, given the known ops pending now.

        Ops called later bound it too, but pruning with them would make the search fail at the start
        rather than where the contradiction becomes visible, and the explanation would be less useful.
        """
        return min([_INF, *(self.bound[i] for i in self.window())])

    def run(self, max_steps: int, deadline: float | None) -> KeyResult:
        """Search for a linearization of the key's known ops.

        In each configuration the known calls before the first return event are tried in list order, then
        the unknown ops called before that return (the earliest unapplied one of each class that might apply).
        The cache maps (known ops linearized, state, counts applied of the free classes) to the fewest pool
        ops used to get there: with as many or more used, that configuration has already failed.
        """
        n_known, nxt, prv, ent_op, ent_ret, match = (
            self.n_known, self.nxt, self.prv, self.ent_op, self.ent_ret, self.match)
        class_ops, call_pos, pool, free = self.class_ops, self.call_pos, self.pool, self.free
        applied = [0] * len(class_ops)
        state = self.encode(self.initial)
        kbits = depth = steps = 0
        stack: list[tuple[int, int, int, int | None]] = []  # (op, its call or the first return, cands index, state)
        cache: dict[tuple[int, int, int | None, tuple[int, ...]], int] = {}
        best = _Stuck(-1, [], self.initial, [], [], 0)  # the deepest dead end
        bound: float | None = None  # version_bound() of the current configuration, computed on demand
        e, c, cands = nxt[self.head], -1, []  # list cursor; then index in cands (-1: still in the list)
        while depth < n_known:
            steps += 1
            if steps > max_steps or (deadline is not None and steps % 4096 == 0 and time.monotonic() > deadline):
                why = f"search budget exceeded ({max_steps} steps)" if steps > max_steps else "timeout"
                return KeyResult(self.key, None, self.ops_count, f"inconclusive: {why}\n{self._explain(best)}", steps)
            k = -1
            if c < 0 and e != -1 and not ent_ret[e]:
                i = ent_op[e]
                allowed, new = self.step(i, state)
                nk = kbits | (1 << i)
            elif c < 0:
                c, cands = 0, self.candidates(state)  # e is the first return: every known call was tried
                continue
            elif c < len(cands):
                k = cands[c]
                c += 1
                a, nk = applied[k], kbits
                if a == len(class_ops[k]) or call_pos[class_ops[k][a]] > e:
                    continue
                i = class_ops[k][a]
                allowed, new = self.step(i, state)
                if allowed:
                    if bound is None:
                        bound = self.version_bound()
                    allowed = new is not None and new // self.m <= bound
            else:
                # Dead end: backtrack.
                if depth > best.depth:
                    best = self._stuck(depth, stack, state, e, applied)
                if not stack:
                    return KeyResult(self.key, False, self.ops_count, self._explain(best), steps)
                i, e, c, state = stack.pop()
                bound = None
                if c < 0:
                    kbits ^= 1 << i
                    depth -= 1
                    for x in (match[e], e):  # put the return and the call back, in the reverse order
                        nxt[prv[x]] = x
                        if nxt[x] != -1:
                            prv[nxt[x]] = x
                    e = nxt[e]
                else:
                    applied[self.cls[i]] -= 1
                    cands = self.candidates(state)
                continue
            if allowed:
                if k >= 0:
                    applied[k] += 1  # tentatively
                lo = ((nk + 1) & ~nk).bit_length() - 1  # all ops below lo are linearized: keep the key small
                key = (lo, nk >> lo, new, tuple(applied[f] for f in free) if free else ())
                used = applied[pool] if pool >= 0 else 0
                seen = cache.get(key)
                allowed = seen is None or used < seen
                if k >= 0:
                    applied[k] -= 1
            if not allowed:
                if c < 0:
                    e = nxt[e]
                continue
            cache[key] = used
            stack.append((i, e, c, state))
            state, kbits, bound = new, nk, None
            if c < 0:
                depth += 1
                for x in (e, match[e]):  # lift the call and its return out of the list
                    nxt[prv[x]] = nxt[x]
                    if nxt[x] != -1:
                        prv[nxt[x]] = prv[x]
            else:
                applied[k] += 1
            e, c = nxt[self.head], -1
        return KeyResult(self.key, True, self.ops_count, "linearizable", steps)

    def _stuck(self, depth: int, stack: list[tuple[int, int, int, int | None]], state: int | None, first_ret: int,
               applied: list[int]) -> _Stuck:
        """Record a dead end; the real value is that of the last write in the prefix (the state keeps codes)."""
        real: State = None
        if state is not None and self.initial is not None:
            value = self.initial[0]
            for i, *_ in reversed(stack):
                op = self.ops[i]
                if op.kind != "read" and op.result in ("ok", "unknown") and op.value is not None:
                    value = op.value
                    break
            real = (value, state // self.m)
        bound, free = self.version_bound(), []
        for u in range(self.n_known, len(self.ops)):
            allowed, new = self.step(u, state)
            if allowed and new is not None and new // self.m <= bound and self.call_pos[u] < first_ret \
                    and self.cls[u] >= 0 and self.rank[u] >= applied[self.cls[u]]:
                free.append(u)
        return _Stuck(depth, [i for i, *_ in stack[-8:]], real, self.window(), free, sum(applied))

    def _explain(self, best: _Stuck) -> str:
        """Where the search got stuck: the longest prefix and the ops that could not follow it."""
        lines = [
            f"longest linearizable prefix: {best.depth} of {self.n_known} ops with a known outcome"
            f" (and {best.applied} unknown-outcome ops taken as applied); initial state {self.initial!r};"
            " its last ops:",
            *(f"  {self.ops[i].describe()}{'  [taken as applied]' if i >= self.n_known else ''}" for i in best.tail),
            f"state after it: {best.state!r}",
            "none of these could be linearized next (nor after any unknown-outcome op that could apply):",
        ]
        lines += [f"  {self.ops[i].describe()}; from that state the model gives: "
                  f"{self._expect(self.ops[i], best.state)}" for i in best.window]
        if best.free:
            lines.append(f"unknown-outcome ops that could still apply there: {len(best.free)}, e.g. "
                         + "; ".join(self.ops[i].describe() for i in best.free[:3]))
        return "\n".join(lines)

    def _expect(self, op: Op, real: State) -> str:
        """What the sequential model answers to ``op`` from state ``real``."""
        if real is None:
            return "not_found"
        if op.kind == "read":
            return f"ok {real!r}"
        if op.kind == "cas" and op.expected != real[1]:
            return f"conflict at version {real[1]}"
        return f"ok, version {self.nv(real[1])}"
