"""Components of the reliability tests (put on PYTHONPATH through a configuration's python_path)."""

from __future__ import annotations

from google.protobuf.wrappers_pb2 import Int64Value, StringValue

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
