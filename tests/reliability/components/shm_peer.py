"""A writer or a reader of large values, as a process of its own (tests/reliability/test_shared_memory_processes.py).

With the launch contract (CAST_*) in its environment:

- ``shm_peer.py write N``: adds "img" (or overwrites it if it exists) and
  overwrites it, N values of 1 MiB in all (value k is :func:`frame` ``(k)``), printing ``WROTE k`` after each and
  ``DONE`` at the end; then it stays until killed or its stdin closes.
- ``shm_peer.py read [hold]``: watches "img" with its entry, printing
  ``WATCHING`` once the watch is confirmed and ``GOT revision k shared`` per
  value (``k``: which frame it is, -1 for bytes that are no frame;
  ``shared``: 1 if it came by shared memory); ``hold`` keeps a view of every
  value. ``FAILED reason`` if the watch fails. It stays until killed or its
  stdin closes.
"""

from __future__ import annotations

import logging
import sys
import threading

from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client.runner import LaunchContract

SIZE = 1 << 20


def frame(k: int) -> bytes:
    """The bytes of frame ``k``: a pattern that differs in every byte position from frame to frame."""
    return bytes((k * 7 + i) % 253 for i in range(253)) * (SIZE // 253)


def which(data: bytes) -> int:
    """The ``k`` of a frame's bytes, or -1."""
    k = next((k for k in range(256) if data[:16] == frame(k)[:16]), -1)
    return k if k >= 0 and data == frame(k) else -1


class Peer(cast.UnmanagedComponent):
    """Says when its watch failed."""

    def watch_failed(self, error: cast.CastError) -> None:
        print(f"FAILED {error}", flush=True)


def main(mode: str, args: list[str]) -> None:
    logging.basicConfig(level=logging.INFO, format="%(name)s %(levelname)s %(message)s")  # the fallback's INFO line
    peer = Peer()
    peer._cast_bind(LaunchContract.from_env().connect())
    if mode == "write":
        for k in range(int(args[0])):
            value = BytesValue(value=frame(k))
            peer.overwrite("img", value) if k or peer.exists("img") else peer.add("img", value)
            print(f"WROTE {k}", flush=True)
        print("DONE", flush=True)
    else:
        held: list[cast.ValueView] = []
        lock = threading.Lock()

        def got(change: cast.WorkingMemoryChange) -> None:
            view = change.view()
            k = which(bytes(view.field(1)))
            with lock:
                print(f"GOT {change.revision} {k} {int(view.shared)}", flush=True)
                if args[:1] == ["hold"]:
                    held.append(view)

        peer.on_change(cast.address_filter("img", cast.Operation.ADD, cast.Operation.OVERWRITE,
                                           include_entry=True), got)
        print("WATCHING", flush=True)
    sys.stdin.read()  # until the test closes it, or kills this process
    peer._cast_close()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
