"""Memory bounds: the bytes a WM may hold, and per-component quotas.

Without a bound, one component adding large entries and never deleting them
grows the server until the machine runs out of memory, for every component.
A write that would pass ``limits.max_total_bytes`` of its WM, or its writer's
quota (entries or bytes, over every WM of the server), is refused with
RESOURCE_EXHAUSTED naming the limit, the usage and the largest holders, and
changes nothing. Only growth is refused: a write that frees room always
passes. Usage is of the latest state (pending writes included) and belongs to
each entry's last writer.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from cast.core.memory import WorkingMemory
from cast.core.records import EntryRecord, Identity, Limits, Quota
from cast.errors import ResourceExhaustedError

__all__ = ["Room", "Tally", "mib"]

Usage = Callable[[], dict[str, list[int]]]
"""Every author's [entries, bytes] over the whole server (read under the host's mutex)."""


@dataclass
class Tally:
    """What a batch's earlier operations add, so that its later ones are checked against it."""

    entries: dict[str, int] = field(default_factory=dict)  # per SA
    bytes: dict[str, int] = field(default_factory=dict)  # per SA
    held: dict[str, list[int]] = field(default_factory=dict)  # per author: [entries, bytes]


def mib(n: int) -> str:
    """Bytes in a form people read: ``12.5 MiB``."""
    return f"{n / (1 << 20):.1f} MiB" if n >= 1 << 20 else f"{n:,} bytes"


def _holders(usage: Mapping[str, list[int]]) -> str:
    top = sorted(usage.items(), key=lambda item: -item[1][1])[:3]
    return ", ".join(f"'{author}' {mib(b)} in {e:,} entries" for author, (e, b) in top) or "none"


class Room:
    """Checks a planned write against the WM bound and its writer's quota."""

    def __init__(self, limits: Limits, quotas: Mapping[str, Quota], usage: Usage) -> None:
        self.limits = limits
        self.quotas = dict(quotas)
        self._usage = usage

    def check(
        self, wm: WorkingMemory, who: Identity, old: EntryRecord | None, new: EntryRecord | None, tally: Tally | None
    ) -> None:
        """RESOURCE_EXHAUSTED if replacing ``old`` by ``new`` (None: absent) passes a bound."""
        sa = wm.name
        old_size = old.size if old is not None else 0
        new_size = new.size if new is not None else 0
        grows = new_size - old_size
        if tally is None and not self.quotas and wm.total_bytes + grows <= self.limits.max_total_bytes:
            return  # the common case: one write, no quotas, room left
        batch_bytes = tally.bytes.get(sa, 0) if tally is not None else 0
        if grows > 0 and wm.total_bytes + batch_bytes + grows > self.limits.max_total_bytes:
            raise ResourceExhaustedError(
                f"subarchitecture '{sa}' would hold {mib(wm.total_bytes + batch_bytes + grows)}, over its bound "
                f"(limits.max_total_bytes = {mib(self.limits.max_total_bytes)}); {who.describe()} holds "
                f"{mib(wm.usage.get(who.component_id, [0, 0])[1])} there; largest holders: {_holders(wm.usage)}; "
                "delete entries you no longer need, or raise the limit in the configuration"
            )
        quota = self.quotas.get(who.component_id)
        if quota is not None and new is not None:
            mine = old is not None and old.author == who.component_id
            gain_entries = 0 if mine else 1
            gain_bytes = new_size - (old_size if mine else 0)
            usage = self._usage()
            entries, held = usage.get(who.component_id, [0, 0])
            if tally is not None:
                extra = tally.held.get(who.component_id, [0, 0])
                entries, held = entries + extra[0], held + extra[1]
            over = (quota.entries and gain_entries > 0 and entries + gain_entries > quota.entries) or (
                quota.bytes and gain_bytes > 0 and held + gain_bytes > quota.bytes
            )
            if over:
                raise ResourceExhaustedError(
                    f"{who.describe()} holds {entries:,} entries and {mib(held)} on this server; this write would "
                    f"pass its quota (components.{who.component_id}.quota: entries {quota.entries or 'unbounded'}, "
                    f"bytes {mib(quota.bytes) if quota.bytes else 'unbounded'}); largest holders: "
                    f"{_holders(usage)}; delete some of its entries, or raise its quota"
                )
        if tally is not None:
            tally.bytes[sa] = batch_bytes + grows
            if old is not None:
                held_old = tally.held.setdefault(old.author, [0, 0])
                held_old[0] -= 1
                held_old[1] -= old_size
            if new is not None:
                held_new = tally.held.setdefault(new.author, [0, 0])
                held_new[0] += 1
                held_new[1] += new_size
