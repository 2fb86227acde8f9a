"""The histories the linearizability checker reads: one operation per JSON line, as a workload records it.

``tests/reliability/linearizability.py`` checks them; the workloads in
``test_linearizability.py`` write them (``dump_history``), and a failing run's
history can be read back (``load_history``) and checked again alone.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any

__all__ = ["KINDS", "RESULTS", "Op", "dump_history", "load_history", "validate"]

KINDS = frozenset({"read", "write", "cas"})
RESULTS = frozenset({"ok", "not_found", "conflict", "unknown"})


@dataclass(frozen=True)
class Op:
    """One operation of a history, as the workload records it (one JSON object per line)."""

    client: str
    key: str
    kind: str  # "read", "write" or "cas"
    value: str | None  # value written (write / cas); None for read
    expected: int | None  # cas only: the expected version
    call: float
    ret: float | None  # None: outcome unknown
    result: str  # "ok", "not_found", "conflict" or "unknown"
    out_value: str | None  # read ok: the value read
    out_version: int | None  # read ok: version read; write/cas ok: new version; cas conflict: current version

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Op:
        """Build an operation from its JSON object (optional fields may be absent)."""

        def opt_int(x: Any) -> int | None:
            return None if x is None else int(x)

        ret = data.get("ret")
        return cls(
            client=str(data["client"]), key=str(data["key"]), kind=str(data["kind"]), value=data.get("value"),
            expected=opt_int(data.get("expected")), call=float(data["call"]),
            ret=None if ret is None else float(ret), result=str(data["result"]),
            out_value=data.get("out_value"), out_version=opt_int(data.get("out_version")),
        )

    def to_json(self) -> dict[str, Any]:
        """The JSON object of this operation (exactly the dataclass's fields)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def describe(self) -> str:
        """A one-line human account: times, client, call and outcome."""
        ret = "?" if self.ret is None else f"{self.ret:.6f}"
        call = {"read": "read()", "write": f"write({self.value!r})"}.get(
            self.kind, f"cas(expected={self.expected}, {self.value!r})")
        out = {"ok": f"ok ({self.out_value!r}, {self.out_version})" if self.kind == "read" else
               f"ok, version {self.out_version}", "conflict": f"conflict at version {self.out_version}"}
        return f"[{self.call:.6f} .. {ret}] client {self.client}: {call} -> {out.get(self.result, self.result)}"


def validate(op: Op) -> None:
    """Raise ValueError if ``op`` is not a well-formed record."""
    problems = []
    if not all(isinstance(x, str) for x in (op.client, op.key, op.value or "", op.out_value or "")):
        problems.append("client, key, value and out_value must be strings")
    if op.kind not in KINDS:
        problems.append(f"kind {op.kind!r}")
    if op.result not in RESULTS:
        problems.append(f"result {op.result!r}")
    if (op.ret is None) != (op.result == "unknown"):
        problems.append("ret must be None exactly when the result is unknown")
    if op.ret is not None and op.ret < op.call:
        problems.append("ret before call")
    if (op.kind == "read") != (op.value is None):
        problems.append("value must be given exactly for write and cas")
    if (op.kind == "cas") != (op.expected is not None):
        problems.append("expected must be given exactly for cas")
    if op.result == "conflict" and (op.kind != "cas" or op.out_version is None):
        problems.append("conflict is for cas only, with out_version")
    if op.result == "ok" and (op.out_version is None or (op.kind == "read" and op.out_value is None)):
        problems.append("ok needs out_version (and out_value for a read)")
    if problems:
        raise ValueError(f"malformed operation {op}: {'; '.join(problems)}")


def load_history(path: str | os.PathLike[str]) -> list[Op]:
    """Read a history: one JSON object per line (blank lines ignored)."""
    ops = []
    with open(path, encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            if line.strip():
                try:
                    ops.append(Op.from_json(json.loads(line)))
                except (ValueError, KeyError, TypeError) as e:
                    raise ValueError(f"{path}:{n}: {e}") from e
    return ops


def dump_history(ops: Iterable[Op], path: str | os.PathLike[str]) -> None:
    """Write a history in the format ``load_history`` reads."""
    with open(path, "w", encoding="utf-8") as f:
        for op in ops:
            f.write(json.dumps(op.to_json()) + "\n")
