"""Closing a client ends every thread of its streams, so that the process can exit.

A thread still inside a gRPC call when the interpreter shuts down can die holding that call's
lock; the call's finaliser then waits for the lock for ever and the process never exits (a
component that "did not stop within 5 s", a script that hangs after its last line). So close()
waits for its own stream threads (heartbeat, watch reader, write replies, decisions) and for the
ones gRPC started for those streams.
"""

from __future__ import annotations

import threading

from google.protobuf.wrappers_pb2 import Int64Value

import cast
from tests.conftest import ServerHandle

ROUNDS = 10  # before the fix about 4 closes in 10 left a thread behind: 10 rounds see it almost surely


class _Managed(cast.ManagedComponent):
    """Opens the decision stream too."""


def test_close_leaves_no_thread_of_its_streams_behind(server: ServerHandle) -> None:
    for i in range(ROUNDS):
        before = set(threading.enumerate())
        component = server.connect(f"closer{i}", "vision", cls=_Managed if i % 2 else None)
        seen = threading.Event()

        def saw(_change: cast.WorkingMemoryChange, seen: threading.Event = seen) -> None:
            seen.set()

        component.on_change(cast.address_filter(f"entry{i}"), saw)
        component.add(f"entry{i}", Int64Value(value=i))  # opens the write stream
        assert seen.wait(10), f"round {i}: the watch did not see the add"
        component._cast_close()
        left = [t.name for t in threading.enumerate() if t not in before and t.is_alive()]
        assert left == [], f"round {i}: threads still running after close(): {left}"
