"""Run inside the server's network namespace: check what the server holds, print one JSON line.

``python netcheck.py ENDPOINT TOKEN released``: wait until the entry ``held`` can be
locked by someone else and no task of ``locker`` is live (its session was lost).
``python netcheck.py ENDPOINT TOKEN state IDS_FILE``: which of the ids exist, and the revision.
"""

from __future__ import annotations

import json
import sys
import time

from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity, LockMode
from cast.core.sessions import ComponentState
from cast.errors import CastError, LockedError


def main() -> int:
    endpoint, token, mode = sys.argv[1:4]
    t = GrpcTransport(endpoint, token, Identity("checker", "vision"), call_timeout=5)
    t.start_session("python", "unmanaged", lambda: ComponentState.RUNNING)  # locks need a live session
    try:
        if mode == "released":
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                try:
                    locked = t.lock("vision", "held", LockMode.O, 5, True)
                    t.unlock("vision", "held")
                    tasks = [x for x in t._call(t._server("vision").tm.ListTasks, _list()).tasks
                             if x.component == "locker"]
                    if locked and not tasks:
                        print(json.dumps({"released": True}), flush=True)
                        return 0
                except LockedError:
                    pass
                time.sleep(0.1)
            print(json.dumps({"released": False}), flush=True)
            return 1
        ids = [line.strip() for line in open(sys.argv[4]) if line.strip()]
        missing = [i for i in ids if not t.exists("vision", i)]
        revision = t.describe().subarchitectures[0].revision
        print(json.dumps({"checked": len(ids), "missing": missing, "revision": revision}), flush=True)
        return 0
    except CastError as exc:
        print(json.dumps({"error": exc.message}), flush=True)
        return 1
    finally:
        t.close()


def _list() -> object:
    from cast.v1 import task_manager_pb2

    return task_manager_pb2.ListTasksRequest(subarchitecture="vision")


if __name__ == "__main__":
    sys.exit(main())
