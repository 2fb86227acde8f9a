"""The Python writer of image-sized entries (bench/shared_memory.py), run as its own process like a component.

`python -m bench.image_writer SIZE N GAP_US` with the launch contract (CAST_*)
in its environment adds the entry "img" (a ``BytesValue`` of SIZE bytes),
overwrites it N times, the i-th at start + i * GAP_US (0: back to back),
each made in a loan (``Component.loan``: in place in the staging area on the
server's host) and then stamped on CLOCK_MONOTONIC (``time.perf_counter_ns``)
just before it, then deletes it (the watchers' end mark) and prints
``{revision: ns}`` of the overwrites. The same as ``cast_bench image-write`` (C++), which M8 runs.
"""

from __future__ import annotations

import json
import sys
import time

from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client.runner import LaunchContract


def main(size: int, frames: int, gap_us: int) -> int:
    """Write, print the stamps, delete."""
    c = cast.UnmanagedComponent()
    c._cast_bind(LaunchContract.from_env().connect())
    fills = [bytes([k + 1]) * size for k in range(2)]  # made before the clock starts; never 0
    c.add("img", BytesValue(value=fills[0]))
    stamps: dict[int, int] = {}
    start = time.perf_counter()
    for i in range(frames):
        if gap_us:
            delay = start + i * gap_us / 1e6 - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        # Made (its bytes copied into its loan) just before its stamp, as the peers' publisher makes its payload
        # (bench.peer_fanout.drive): a fresh frame is in the cache when it is published.
        loan = c.loan(BytesValue(), "value", size)
        loan.buffer[:] = fills[i % 2]
        t = time.perf_counter_ns()
        stamps[c.overwrite("img", loan).revision] = t
    c.delete_entry("img")
    print(json.dumps(stamps), flush=True)
    c._cast_close()
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])))
