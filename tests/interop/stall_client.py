"""Every kind of call at once against a server that stopped answering: the Python side of test_hung_server.py.

The same stdin/stdout protocol as cpp_client/tests/components/cast_test_stall.cc (which describes
it) and cast.itest.Stall: one connection per call (``cast.connect``, tokens minted from
``$CAST_SECRET``), call timeout ``$CAST_STALL_CALL_TIMEOUT_MS``, lock timeout
``$CAST_STALL_LOCK_TIMEOUT_MS``.

    python stall_client.py PREFIX
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from cast_testing_pb2 import Counter

import cast
from cast.core.records import LockMode
from cast.errors import AlreadyExistsError, CastError

KINDS = ("add", "add_async", "overwrite", "delete", "batch", "lock", "try_lock", "unlock", "get", "get_all",
         "exists", "watch", "report")
_out = threading.Lock()


def say(line: dict[str, Any]) -> None:
    """One JSON answer on stdout."""
    with _out:
        print(json.dumps(line), flush=True)


def counter(value: int) -> Counter:
    """A test value."""
    return Counter(writer="python", value=value)


def main(prefix: str) -> int:
    """Run the protocol until "quit"."""
    call_timeout = int(os.environ.get("CAST_STALL_CALL_TIMEOUT_MS", "3000")) / 1000
    lock_timeout = int(os.environ.get("CAST_STALL_LOCK_TIMEOUT_MS", "4000")) / 1000

    def open_(who: str) -> cast.Connection:
        return cast.connect(component_id=f"{prefix}-{who}", subarchitecture="vision", call_timeout=call_timeout)

    p = prefix
    writer, watcher = open_("writer"), open_("watcher")
    seen: list[int] = []
    seen_changed = threading.Condition()

    def saw(change: cast.WorkingMemoryChange) -> None:
        with seen_changed:
            seen.append(change.revision)
            seen_changed.notify_all()

    watcher.on_change([cast.operation_filter(local=True)], saw)
    conns = {kind: open_(kind) for kind in KINDS}
    # Every stream a call uses is open before the stall, as in a component that has been running.
    conns["add"].add(f"{p}-warm-add", counter(0))
    conns["add_async"].add_async(f"{p}-warm-async", counter(0)).result()
    conns["overwrite"].add(f"{p}-ow", counter(0))
    conns["delete"].add(f"{p}-del", counter(0))
    conns["batch"].add(f"{p}-warm-batch", counter(0))
    conns["lock"].add(f"{p}-lk", counter(0))
    conns["lock"].lock(f"{p}-lk", LockMode.O).unlock()
    conns["try_lock"].add(f"{p}-warm-try", counter(0))
    conns["unlock"].add(f"{p}-ul", counter(0))
    conns["unlock"].lock(f"{p}-ul", LockMode.O)  # held: "unlock" releases it during the stall
    conns["get"].exists(f"{p}-ow")
    conns["watch"].on_change([cast.address_filter(f"{p}-ow")], lambda change: None)  # its watch stream is open
    conns["report"].report("warm", 1)
    say({"ready": True})

    calls: dict[str, Callable[[], object]] = {
        "add": lambda: conns["add"].add(f"{p}-stalled-add", counter(1)),
        "add_async": lambda: conns["add_async"].add_async(f"{p}-stalled-async", counter(1)).result(),
        "overwrite": lambda: conns["overwrite"].overwrite(f"{p}-ow", counter(1)),
        "delete": lambda: conns["delete"].delete_entry(f"{p}-del"),
        "batch": lambda: conns["batch"].batch([("add", f"{p}-stalled-batch", counter(2))]),
        "lock": lambda: conns["lock"].lock(f"{p}-lk", LockMode.O, timeout=lock_timeout),
        "try_lock": lambda: conns["try_lock"].try_lock(f"{p}-lk", LockMode.O),
        "unlock": lambda: conns["unlock"].unlock(f"{p}-ul"),
        "get": lambda: conns["get"].get(f"{p}-ow", Counter),
        "get_all": lambda: conns["get_all"].get_all(Counter),
        "exists": lambda: conns["exists"].exists(f"{p}-ow"),
        "watch": lambda: conns["watch"].on_change([cast.operation_filter(local=True)], lambda change: None),
        "report": lambda: conns["report"].report("stalled", 1),
    }
    acked = 0
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] == "acked":
            ids = []
            for i in range(int(words[1])):
                ids.append(f"{p}-acked-{acked}")
                writer.add(ids[-1], counter(i))
                acked += 1
            say({"acked": ids})
        elif words[0] == "stall":
            start = time.monotonic()

            threads = [threading.Thread(target=timed, args=(*item, start)) for item in calls.items()]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            say({"stalled": True})
        elif words[0] == "recover":
            threads = [threading.Thread(target=lambda k=kind: say(recover(conns[k], k, p))) for kind in KINDS]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            say({"recovered_all": True})
        elif words[0] == "expect":
            with seen_changed:
                seen_changed.wait_for(lambda at=int(words[1]): any(r >= at for r in seen), 30)
                say({"revisions": list(seen)})
        elif words[0] == "quit":
            break
    for conn in (*conns.values(), watcher, writer):
        conn.close()
    return 0


def timed(kind: str, call: Callable[[], object], start: float) -> None:
    """Make one call; say how long it took from ``start`` and how it ended."""
    out: dict[str, Any] = {"call": kind}
    try:
        call()
        out.update(ms=round((time.monotonic() - start) * 1000), error=None)
    except CastError as exc:
        out.update(ms=round((time.monotonic() - start) * 1000), error=type(exc).__name__, message=str(exc))
    say(out)


def recover(conn: cast.Connection, kind: str, p: str) -> dict[str, Any]:
    """Write on ``conn`` until a write succeeds (60 s at most); how long it took and how many tries."""
    start = time.monotonic()
    tries = 0
    last = ""
    while time.monotonic() - start < 60:
        tries += 1
        try:
            conn.add(f"{p}-recovered-{kind}", counter(3))
            last = ""
            break
        except AlreadyExistsError:
            last = ""  # an earlier try was applied after all
            break
        except CastError as exc:
            last = f"{type(exc).__name__}: {exc}"
            time.sleep(0.05)
    out: dict[str, Any] = {"recovered": kind, "ms": round((time.monotonic() - start) * 1000), "tries": tries}
    if last:
        out["error"] = last
    return out


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
