"""The Python watcher of M8 (bench/images.py), run as its own process like a component.

`python -m bench.image_watcher queue|latest` with the launch contract (CAST_*) in
its environment watches the entry "img" of its SA with the entry carried
(``include_entry``) and reads every byte of each image where the library put
it: ``change.view().field(1)`` (the ``bytes`` field of the ``BytesValue``, a
read-only memoryview of the server's shared memory on its host, of the received
bytes elsewhere), summed with numpy (bench.checksum) as a consumer of frames
would read them. It prints ``ready`` once the watch is confirmed, and at the
DELETE of "img" (the writer's end mark) one line ``{"stamps": {revision: ns},
"bytes": B, "events": E, "skipped": S, "checksum": C, "shared": H}``:
CLOCK_MONOTONIC (``time.perf_counter_ns``) once each overwrite's bytes were all
read, the image bytes read, the events received (the add and the delete too),
the changes a latest watch was told it skipped, the sum of the overwrites'
checksums modulo 2**64 and how many of them were lent by shared memory. The C++
and Java watchers (cast_bench / cast.bench.Bench ``image-watch``) print the
same.
"""

from __future__ import annotations

import json
import sys
import threading
import time

import cast
from bench.checksum import MOD, word_sum
from cast.client.runner import LaunchContract


class _Watcher(cast.UnmanagedComponent):
    """Ends the wait when the watch fails (a queue watcher left behind the history), rather than at a timeout."""

    def __init__(self) -> None:
        super().__init__()
        self.ended = threading.Event()

    def watch_failed(self, error: cast.CastError) -> None:
        print(f"image_watcher: the watch failed: {error}", file=sys.stderr, flush=True)
        self.ended.set()


def main(delivery: str) -> int:
    """Watch "img" until its DELETE, then print what arrived."""
    c = _Watcher()
    c._cast_bind(LaunchContract.from_env().connect())
    stamps: dict[int, int] = {}
    totals = {"bytes": 0, "events": 0, "skipped": 0, "checksum": 0, "shared": 0}
    ended = c.ended

    def arrived(change: cast.WorkingMemoryChange) -> None:
        totals["events"] += 1
        totals["skipped"] += change.skipped
        if change.operation is cast.Operation.DELETE:
            ended.set()
            return
        with change.view() as view:  # given back at the end of the block: the server may reuse its place
            pixels = view.field(1)
            checksum = word_sum(pixels)
            # Every byte read: the stamp, before the value is given back (as the C++ watcher and the peers'
            # subscribers stamp before they let their buffer go).
            t = time.perf_counter_ns()
            size, shared = len(pixels), view.shared
            del pixels
        if change.operation is cast.Operation.OVERWRITE:
            stamps[change.revision] = t
            totals["bytes"] += size
            totals["checksum"] = (totals["checksum"] + checksum) % MOD
            totals["shared"] += shared

    c.on_change(cast.address_filter("img", include_entry=True), arrived, delivery=delivery)
    print("ready", flush=True)
    ended.wait(300)
    print(json.dumps({"stamps": stamps, **totals}), flush=True)
    c._cast_close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
