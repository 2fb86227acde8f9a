"""Components used by the integration tests; each runs as its own process via `python -m cast.run`."""

from __future__ import annotations

import time
from typing import Any

from cast_testing_pb2 import Counter, Pose

import cast


class Writer(cast.UnmanagedComponent):
    """Adds ``count`` entries, overwrites each once, deletes every third; then stops."""

    def configure(self, args: dict[str, Any]) -> None:
        self.count = int(args.get("count", 10))

    def run(self) -> None:
        added = []
        for i in range(self.count):
            entry_id = self.new_id()
            added.append((entry_id, self.add(entry_id, Counter(writer=self.component_id, value=i)).version))
        for i, (entry_id, version) in enumerate(added):
            version = self.overwrite(entry_id, Counter(writer=self.component_id, value=i + 1000),
                                     expected_version=version).version
            if i % 3 == 0:
                self.delete(entry_id, expected_version=version)
        self.request_stop()


class CrossReader(cast.UnmanagedComponent):
    """Reads every Pose of another SA and writes their labels into its own SA."""

    def configure(self, args: dict[str, Any]) -> None:
        self.source = str(args["source"])

    def run(self) -> None:
        labels = sorted(e.value.label for e in self.get_all(Pose, subarchitecture=self.source))
        self.add("summary", Pose(label=",".join(labels), tags=[e for e in labels]))
        self.request_stop()


class Intruder(cast.UnmanagedComponent):
    """Tries to write into another SA and records what happened in its own."""

    def configure(self, args: dict[str, Any]) -> None:
        self.target = str(args["target"])

    def run(self) -> None:
        try:
            self.add("goal", Pose(label="from " + self.component_id), subarchitecture=self.target)
            outcome = "written"
        except cast.PermissionDeniedError as exc:
            outcome = f"refused: {exc.message}"
        self.add(f"outcome-{self.component_id}", Pose(label=outcome))
        self.request_stop()


class Proposer(cast.ManagedComponent):
    """Proposes one task; when adopted, writes a marker entry, completes the task and stops."""

    def start(self) -> None:
        self.task = self.propose_task("recognise", Pose(label="cube"), priority=3)

    def task_adopted(self, task: cast.Task) -> None:
        data = task.data(Pose)
        self.add(f"adopted-{task.task_id}", Pose(label=data.label if data else "", tags=[task.name]))
        self.task_complete(task, cast.TaskOutcome.SUCCEEDED, "recognised")
        self.request_stop()


class StopRecorder(cast.UnmanagedComponent):
    """Writes an entry from stop(), so a test can see that SIGTERM reached the hook."""

    def start(self) -> None:
        self.add("started", Pose(label="started"))

    def stop(self) -> None:
        self.add("stopped", Pose(label="stop hook ran"))


class Crasher(cast.UnmanagedComponent):
    """Locks an entry and then dies, leaving its lock behind for the server to release."""

    def run(self) -> None:
        self.add("held", Pose(label="locked by a crasher"))
        self.lock("held", cast.LockMode.ODR)
        self.add("ready", Pose())
        self.wait_for_stop()


class SignalUnderLock(cast.UnmanagedComponent):
    """Calls the runner's SIGTERM handler while holding the lock of its stop event.

    That is the state of the main thread when a second signal arrives during the
    first one's handling: a handler that takes the lock deadlocks here.
    """

    def run(self) -> None:
        import signal

        handler = signal.getsignal(signal.SIGTERM)
        assert callable(handler)
        with self._stopping._cond:  # type: ignore[attr-defined]
            handler(signal.SIGTERM, None)
        self.add("handled", Pose(label="the handler returned"))


class Announcer(cast.UnmanagedComponent):
    """Takes a second to start (its first heartbeat says STARTING), says RUNNING as run() begins, waits."""

    def start(self) -> None:
        time.sleep(1.0)

    def run(self) -> None:
        print("RUNNING", flush=True)
        self.wait_for_stop()
