"""What one watcher (or subscriber) received, from the writer's stamps and its own: pure functions.

Used by M8 (bench/images.py) and the peers' large-value runs
(bench/zenoh_peer.py, bench/redis_peer.py). Stamps are CLOCK_MONOTONIC
nanoseconds taken in different processes of one machine: the writer's just
before each write, the watcher's in its callback, keyed by revision (CAST) or
sequence number (the peers).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from bench.harness import summary_us

__all__ = ["latencies_us", "ordinal", "parse_watcher", "settling", "totals", "watcher_figures"]


def parse_watcher(doc: Mapping[str, Any]) -> dict[str, Any]:
    """A watcher's printed JSON line, with its stamps' keys as integers."""
    out = {
        "stamps": {int(k): int(v) for k, v in doc["stamps"].items()},
        "bytes": int(doc["bytes"]),
        "events": int(doc.get("events", len(doc["stamps"]))),
        "skipped": int(doc.get("skipped", 0)),
    }
    for optional in ("checksum", "shared"):  # what M8's readers of every byte add (bench.checksum)
        if optional in doc:
            out[optional] = int(doc[optional])
    return out


def settling(count: int) -> int:
    """How many of ``count`` measured writes, the first, the latencies leave out as warm-up (a tenth, at most 30)."""
    return min(30, count // 10)


def latencies_us(sent: Mapping[int, int], stamps: Mapping[int, int]) -> list[float]:
    """Write -> arrival (µs) of each write in ``sent`` that arrived, in key order."""
    return [(stamps[k] - t0) / 1e3 for k, t0 in sorted(sent.items()) if k in stamps]


def watcher_figures(sent: Mapping[int, int], got: Mapping[str, Any], extra_events: int = 0) -> dict[str, Any]:
    """Latency (µs), counts and delivered MB/s of one watcher.

    ``sent``: key -> write stamp (ns) of every measured write; ``got``: as
    :func:`parse_watcher` returns. ``extra_events`` is how many events the
    watcher also received that are not in ``sent`` (CAST's add and delete of
    the entry). Lost is what the watcher neither received nor was told it
    skipped (a latest watch reports what it skipped, which is not lost).
    MB/s (10**6 bytes) is the value bytes received over the time from the first
    write to the last arrival. ``samples_us`` holds the latencies themselves
    (bench/images.py's judged phase splits them into halves).
    """
    stamps: Mapping[int, int] = got["stamps"]
    samples = latencies_us(sent, stamps)
    lost = len(sent) + extra_events - got["events"] - got["skipped"]
    span_ns = (max(stamps.values()) - min(sent.values())) if stamps and sent else 0
    latency = summary_us(samples) if samples else {"p50_us": math.nan, "p99_us": math.nan, "mean_us": math.nan}
    return {
        **latency,
        "samples_us": samples,
        "received": len(samples),
        "skipped": got["skipped"],
        "lost": lost,
        "mb_per_s": round(got["bytes"] / span_ns * 1e3, 1) if span_ns > 0 else 0.0,
    }


def totals(sent: Mapping[int, int], watchers: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """All watchers together: value bytes delivered per second (MB/s) from the first write to the last arrival."""
    last = max((max(w["stamps"].values()) for w in watchers if w["stamps"]), default=0)
    first = min(sent.values()) if sent else 0
    delivered = sum(w["bytes"] for w in watchers)
    return {"mb_per_s": round(delivered / (last - first) * 1e3, 1) if last > first else 0.0, "bytes": delivered}


def ordinal(number: int) -> str:
    """``number`` as a word (first, second, ...): how the benchmarks name a round."""
    words = ("first", "second", "third", "fourth", "fifth")
    return words[number - 1] if 1 <= number <= len(words) else f"{number}th"
