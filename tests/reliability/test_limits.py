"""Limits from the configuration, each refused over the wire with a clear status naming the limit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import grpc
from cast_testing_pb2 import Counter
from google.protobuf import any_pb2
from google.protobuf.wrappers_pb2 import BytesValue

from cast.core.records import Limits, LockMode
from cast.v1 import entry_pb2, working_memory_pb2, working_memory_pb2_grpc
from tests.conftest import PYTHONPATH, SECRET, VENV_BIN, register_session
from tests.reliability.conftest import wait_for

COMPONENTS = Path(__file__).parent / "components"

LIMITS = {"max_value_bytes": 64, "max_entries": 3, "max_watchers": 2, "max_lock_waiters": 1,
          "max_batch_operations": 4}


def _value(size: int) -> any_pb2.Any:
    packed = any_pb2.Any()
    packed.Pack(Counter(writer="x" * size))
    return packed


def _status(fn: Any, *args: Any, **kwargs: Any) -> tuple[grpc.StatusCode, str]:
    try:
        fn(*args, **kwargs)
    except grpc.RpcError as exc:
        return exc.code(), exc.details()
    return grpc.StatusCode.OK, ""


def test_each_configured_limit_is_a_clear_refusal_over_the_wire(server_factory: Any) -> None:
    handle = server_factory({"system": "lim", "subarchitectures": {"vision": {}}, "limits": LIMITS})
    ch = grpc.insecure_channel(handle.endpoint)
    wm = working_memory_pb2_grpc.WorkingMemoryStub(ch)
    md = (("authorization", f"Bearer {handle.token('a', 'vision')}"),)
    md_b = (("authorization", f"Bearer {handle.token('b', 'vision')}"),)
    md_c = (("authorization", f"Bearer {handle.token('c', 'vision')}"),)
    for m in (md, md_b, md_c):
        register_session(ch, m)  # locks need a live session

    def addr(i: str) -> entry_pb2.EntryAddress:
        return entry_pb2.EntryAddress(id=i, subarchitecture="vision")

    streams: list[Any] = []
    try:
        # Value size: INVALID_ARGUMENT naming limits.max_value_bytes.
        code, details = _status(wm.Add, working_memory_pb2.AddRequest(address=addr("big"), value=_value(100)),
                                metadata=md)
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "limits.max_value_bytes" in details
        # Entries per WM: RESOURCE_EXHAUSTED naming limits.max_entries.
        for i in range(3):
            wm.Add(working_memory_pb2.AddRequest(address=addr(f"e{i}"), value=_value(1)), metadata=md)
        code, details = _status(wm.Add, working_memory_pb2.AddRequest(address=addr("e3"), value=_value(1)),
                                metadata=md)
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "limits.max_entries" in details
        # Batch size: INVALID_ARGUMENT naming the limit.
        ops = [working_memory_pb2.BatchOperation(delete=working_memory_pb2.DeleteRequest(address=addr("e0")))] * 5
        code, details = _status(wm.Batch, working_memory_pb2.BatchRequest(operations=ops), metadata=md)
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "limit of 4" in details
        # Lock waiters: the second blocked waiter is refused with RESOURCE_EXHAUSTED.
        wm.Lock(working_memory_pb2.LockRequest(address=addr("e0"), mode=LockMode.O), metadata=md)
        waiter = wm.Lock.future(working_memory_pb2.LockRequest(address=addr("e0"), mode=LockMode.O),
                                metadata=md_b, timeout=30)
        wait_for(lambda: "pending" in _status(wm.Lock, working_memory_pb2.LockRequest(
            address=addr("e0"), mode=LockMode.O), metadata=md_c, timeout=5)[1] or waiter.done(), what="waiter")
        code, details = _status(wm.Lock, working_memory_pb2.LockRequest(address=addr("e0"), mode=LockMode.O),
                                metadata=md_c, timeout=5)
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "limits.max_lock_waiters" in details
        wm.Unlock(working_memory_pb2.UnlockRequest(address=addr("e0")), metadata=md)
        assert waiter.result().depth == 1  # the admitted waiter got the lock
        # Watchers per server: the third stream is refused with RESOURCE_EXHAUSTED.
        for _ in range(2):
            requests: list[working_memory_pb2.WatchRequest] = []
            gate = threading.Event()

            def gen(gate: threading.Event = gate, requests: list[Any] = requests) -> Any:
                yield from requests
                gate.wait()

            call = wm.Watch(gen(), metadata=md)
            streams.append((call, gate))
        wait_for(lambda: "limits.max_watchers" in _status(lambda: list(wm.Watch(iter([]), metadata=md)))[1],
                 what="the watcher limit")
        code, details = _status(lambda: list(wm.Watch(iter([]), metadata=md)))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED
    finally:
        for call, gate in streams:
            gate.set()
            call.cancel()
        ch.close()


def test_default_limits_are_far_from_ordinary_use() -> None:
    """The defaults (documented in docs/reliability.md) leave room for any test or demo here."""
    d = Limits()
    assert d.max_value_bytes >= 8 * 1024 * 1024 and d.max_entries >= 1_000_000
    assert d.max_watchers >= 10_000 and d.max_lock_waiters >= 10_000 and d.max_batch_operations >= 10_000


def test_a_runaway_writer_is_refused_at_the_bound_while_the_server_and_others_go_on(server_factory: Any) -> None:
    handle = server_factory({"system": "run", "subarchitectures": {"vision": {}},
                             "limits": {"max_total_bytes": 4 << 20}})
    runaway = subprocess.Popen([sys.executable, "-m", "cast.run", "rel_components:Runaway"],
                               env={**handle.env("runaway", "vision"), "PYTHONPATH": f"{PYTHONPATH}:{COMPONENTS}"},
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    other = handle.connect("other", "vision")
    try:
        out, _ = runaway.communicate(timeout=120)
        refused = [line for line in out.splitlines() if line.startswith("REFUSED")]
        assert refused, out
        assert "limits.max_total_bytes = 4.0 MiB" in refused[0] and "'runaway'" in refused[0], refused[0]
        # The server and the other components go on: a small write, reads, and room freed by a delete.
        version = other.add("note", Counter(value=1)).version
        assert other.get_entry("note", Counter).version == version
        held = [e for e in other.get_all(BytesValue) if e.author == "runaway"]
        assert 50 <= len(held) <= 64
        boss = handle.connect("boss", "vision", privileged=True)
        boss.delete_entry(held[0].id)
        boss.add("fits", BytesValue(value=b"b" * 65536))
        boss._cast_close()
        out = subprocess.run([str(VENV_BIN / "cast"), "components", "--json", "--endpoint", handle.endpoint],
                             env={**os.environ, "CAST_SECRET": SECRET}, capture_output=True, text=True, timeout=60)
        usage = {c["id"]: (c["entries"], c["bytes"]) for c in json.loads(out.stdout)}
        assert usage["runaway"][0] == len(held) - 1 and usage["runaway"][1] > (len(held) - 1) * 65536, usage
    finally:
        runaway.kill()
        other._cast_close()
