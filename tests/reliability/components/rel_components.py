"""Components of the reliability tests (put on PYTHONPATH through a configuration's python_path)."""

from __future__ import annotations

import threading

from google.protobuf.wrappers_pb2 import BytesValue, Int64Value, StringValue

import cast


class Ticker(cast.UnmanagedComponent):
    """Overwrites ``tick`` every 0.1 s; the first failure is written to ``tick-error`` (if it still can)."""

    def run(self) -> None:
        self.add("tick", Int64Value(value=0))
        i = 0
        while not self.wait_for_stop(0.1):
            i += 1
            try:
                self.overwrite("tick", Int64Value(value=i))
            except cast.CastError as exc:
                self.log.error("tick %d failed: %s", i, exc)
                try:
                    self.add("tick-error", StringValue(value=f"{exc.code}: {exc.message}"))
                except cast.CastError:
                    pass
                return


class NetWriter(cast.UnmanagedComponent):
    """Adds ``count`` entries ``n<i>``, printing ``ACK <id> <revision>`` once each is acknowledged."""

    def run(self) -> None:
        count = int(self._args.get("count", 200))
        for i in range(count):
            if not self.running:
                return
            while True:
                try:
                    result = self.add(f"n{i}", Int64Value(value=i))
                    print(f"ACK n{i} {result.revision}", flush=True)
                    break
                except cast.AlreadyExistsError:
                    break  # applied, acknowledgement lost with the link: not counted as acknowledged
                except cast.CastError:
                    self.wait_for_stop(0.1)  # the link is down: try again
            self.wait_for_stop(0.02)
        print("DONE", flush=True)

    def configure(self, args: dict[str, object]) -> None:
        self._args = args


class NetWatcher(cast.UnmanagedComponent):
    """Prints ``EV <revision> <id>`` for every change of its own SA, and ``FAILED`` on a resync signal."""

    def start(self) -> None:
        self.on_change(cast.ChangeFilter(subarchitecture=self.subarchitecture), self.changed)
        print("WATCHING", flush=True)

    def changed(self, change: cast.WorkingMemoryChange) -> None:
        print(f"EV {change.revision} {change.id}", flush=True)

    def watch_failed(self, error: cast.CastError) -> None:
        print(f"FAILED {error.code}", flush=True)


class NetLocker(cast.ManagedComponent):
    """Adds and locks ``held`` and proposes a task it never completes; prints LOCKED and ADOPTED."""

    def start(self) -> None:
        if not self.exists("held"):
            self.add("held", Int64Value(value=1))
        self.lock("held", cast.LockMode.OD)
        print("LOCKED", flush=True)
        self.propose_task("hold")

    def task_adopted(self, task: cast.Task) -> None:
        print(f"ADOPTED {task.task_id}", flush=True)


class Churner(cast.ManagedComponent):
    """Read-modify-write under a lock: ``shared-<k>``'s value counts its overwrites, checked by version.

    Proposes a task now and then and holds each adopted task for a while, so a kill finds
    locks and tasks to release.
    """

    def configure(self, args: dict[str, object]) -> None:
        self.keys = int(args.get("keys", 3))  # type: ignore[call-overload]

    def start(self) -> None:
        for k in range(self.keys):
            try:
                self.add(f"shared-{k}", Int64Value(value=0))
            except cast.AlreadyExistsError:
                pass

    def run(self) -> None:
        i = 0
        while self.running:
            i += 1
            key = f"shared-{i % self.keys}"
            try:
                with self.lock(key, cast.LockMode.OD, timeout=5):
                    entry = self.get_entry(key, Int64Value)
                    self.overwrite(key, Int64Value(value=entry.value.value + 1), expected_version=entry.version)
                if i % 20 == 0:
                    self.propose_task(f"job-{i}")
            except cast.CastError as exc:
                self.log.info("round %d: %s", i, exc)
            self.wait_for_stop(0.01)

    def task_adopted(self, task: cast.Task) -> None:
        threading.Timer(0.5, self._finish, args=(task,)).start()

    def _finish(self, task: cast.Task) -> None:
        try:
            self.task_complete(task)
        except cast.CastError:
            pass


class Auditor(cast.UnmanagedComponent):
    """Checks every change of a ``shared-*`` entry: its value advances exactly as its version does.

    Each overwrite adds 1 to both, so a lost update (two writers both overwriting the value they
    read) shows as a version step without a value step. Versions start at the server's version
    floor, not at 0, so only steps are compared.
    """

    def start(self) -> None:
        self.checked = 0
        self.violations = 0
        self.last: dict[str, tuple[int, int]] = {}  # id -> (value, version) of the last change seen
        self.on_change(cast.local_type_filter(Int64Value, include_entry=True), self.check)

    def check(self, change: cast.WorkingMemoryChange) -> None:
        if not change.id.startswith("shared-") or change.operation is cast.Operation.DELETE:
            return
        entry = change.entry(Int64Value)
        seen = (entry.value.value, entry.version)
        last = self.last.get(change.id)
        self.last[change.id] = seen
        if last is None:
            return
        self.checked += 1
        if seen[0] - last[0] != seen[1] - last[1]:
            self.violations += 1
            self.log.error("inconsistent entry %s: value %d -> %d while version %d -> %d", change.id, last[0],
                           seen[0], last[1], seen[1])

    def run(self) -> None:
        self.add("audit", StringValue(value="0 0"))
        while not self.wait_for_stop(0.2):
            self.overwrite("audit", StringValue(value=f"{self.checked} {self.violations}"))


class Runaway(cast.UnmanagedComponent):
    """Adds 64 KiB entries and never deletes them, until the server refuses; prints REFUSED with the reason."""

    def run(self) -> None:
        added = 0
        while not self.wait_for_stop(0):
            try:
                self.add(self.new_id(), BytesValue(value=b"r" * 65536))
                added += 1
            except cast.ResourceExhaustedError as exc:
                print(f"REFUSED after {added}: {exc.message}", flush=True)
                self.request_stop()
                return
