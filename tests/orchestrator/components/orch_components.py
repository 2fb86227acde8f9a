"""Components used by the orchestrator and CLI tests (put on PYTHONPATH through a config's python_path)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from google.protobuf.wrappers_pb2 import BoolValue, Int64Value, StringValue

import cast


class Producer(cast.UnmanagedComponent):
    """Adds ``count`` StringValue items ``item-<i>`` to its own SA."""

    def configure(self, args: dict[str, Any]) -> None:
        self.count = int(args.get("count", 3))

    def run(self) -> None:
        for i in range(self.count):
            self.add(f"item-{i}", StringValue(value=f"item {i} from {self.subarchitecture}"))
        self.wait_for_stop()


class Worker(cast.ManagedComponent):
    """For each item added anywhere, proposes a task; when adopted, writes ``result-<i>`` into its own SA.

    Items already in ``source_sa`` when it starts are picked up too (watch first, then read).
    """

    def configure(self, args: dict[str, Any]) -> None:
        self.source = str(args.get("source_sa", ""))
        self.seen: set[str] = set()
        self.mutex = threading.Lock()

    def start(self) -> None:
        self.on_change(cast.global_type_filter(StringValue, cast.Operation.ADD), self.item)
        if self.source:
            for entry in self.get_all(StringValue, subarchitecture=self.source):
                self.propose_once(entry.id)

    def item(self, change: cast.WorkingMemoryChange) -> None:
        self.propose_once(change.id)

    def propose_once(self, entry_id: str) -> None:
        with self.mutex:  # start() and the dispatcher both get here
            if not entry_id.startswith("item-") or entry_id in self.seen:
                return
            self.seen.add(entry_id)
        self.propose_task(f"work {entry_id}", StringValue(value=entry_id))

    def task_adopted(self, task: cast.Task) -> None:
        data = task.data(StringValue)
        assert data is not None
        index = int(data.value.removeprefix("item-"))
        self.add(f"result-{index}", Int64Value(value=index * index))
        self.task_complete(task, cast.TaskOutcome.SUCCEEDED)


class Reporter(cast.UnmanagedComponent):
    """When ``expected`` results exist anywhere, adds BoolValue ``report`` to its own SA."""

    def configure(self, args: dict[str, Any]) -> None:
        self.expected = int(args.get("expected", 3))
        self.source = str(args.get("source_sa", ""))
        self.seen: set[str] = set()
        self.mutex = threading.Lock()

    def start(self) -> None:
        self.on_change(cast.global_type_filter(Int64Value, cast.Operation.ADD), self.result)
        if self.source:
            for entry in self.get_all(Int64Value, subarchitecture=self.source):
                self.count(entry.id)

    def result(self, change: cast.WorkingMemoryChange) -> None:
        self.count(change.id)

    def count(self, entry_id: str) -> None:
        with self.mutex:  # start() and the dispatcher both get here
            if not entry_id.startswith("result-") or entry_id in self.seen:
                return
            self.seen.add(entry_id)
            complete = len(self.seen) == self.expected
        if complete:
            self.add("report", BoolValue(value=True))


class Crasher(cast.ManagedComponent):
    """First run: locks an entry, gets a task adopted, then dies. Later runs: shows the TM is free again."""

    def configure(self, args: dict[str, Any]) -> None:
        self.marker = Path(args["marker"])

    def run(self) -> None:
        if not self.marker.exists():
            self.add("held", StringValue(value="locked by the first incarnation"))
            self.lock("held", cast.LockMode.OD)
            self.propose_task("doomed")
            self.wait_for_stop()
        else:
            self.propose_task("after-restart")
            self.wait_for_stop()

    def task_adopted(self, task: cast.Task) -> None:
        if task.name == "doomed":
            self.marker.write_text(str(os.getpid()))
            print("holding a lock and a task; crashing now", flush=True)
            os._exit(3)
        self.add("adopted-after-restart", StringValue(value=task.task_id))
        self.task_complete(task)


class Checker(cast.UnmanagedComponent):
    """Overwrites ``held`` (in ``target_sa``) once nobody locks it: proof the crashed holder's lock is gone."""

    def configure(self, args: dict[str, Any]) -> None:
        self.target = str(args["target_sa"])
        self.marker = Path(args["marker"])

    def run(self) -> None:
        while not self.wait_for_stop(0.05):
            if not self.marker.exists():  # the crasher has not crashed yet
                continue
            try:
                if self.exists("held", subarchitecture=self.target) and self.try_lock(
                    "held", subarchitecture=self.target
                ):
                    self.overwrite("held", StringValue(value="taken over"), subarchitecture=self.target)
                    self.unlock("held", subarchitecture=self.target)
                    return
            except cast.CastError:
                pass


class Joiner(cast.UnmanagedComponent):
    """Adds ``joined-<id>`` to its own SA (started by hand with `cast token`)."""

    def run(self) -> None:
        self.add(f"joined-{self.component_id}", StringValue(value=self.component_id))
        self.wait_for_stop()


class Spawner(cast.UnmanagedComponent):
    """Starts a child process that would outlive it, and records the child's pid."""

    def run(self) -> None:
        child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(300)"])
        self.add("child-pid", Int64Value(value=child.pid))
        self.wait_for_stop()


class Stubborn(cast.UnmanagedComponent):
    """Does not finish stop() in time: the orchestrator must kill it."""

    def stop(self) -> None:
        time.sleep(120)


class Failing(cast.UnmanagedComponent):
    """run() raises at once: the runner exits 1."""

    def run(self) -> None:
        raise RuntimeError("broken on purpose")


class FailingStart(cast.UnmanagedComponent):
    """start() raises: the runner exits 1 before the start barrier."""

    def start(self) -> None:
        raise RuntimeError("broken on purpose")


class Recorder(cast.UnmanagedComponent):
    """Prints when its stop() is called (the order of shutdown shows in the output)."""

    def stop(self) -> None:
        print("stop() called", flush=True)


class Quick(cast.UnmanagedComponent):
    """Does its one write and stops by itself, before the orchestrator looks."""

    def run(self) -> None:
        self.add(self.new_id(), Int64Value(value=1))
        self.request_stop()


class Lingering(cast.UnmanagedComponent):
    """Exits at stop() without closing its connections, which a detached child keeps open ``linger`` s more.

    The servers see its streams end only when the child exits: the orchestrator's final summary
    must wait for that rather than show the session still running.
    """

    def configure(self, args: dict[str, Any]) -> None:
        self.linger = float(args.get("linger", 1.0))

    def stop(self) -> None:
        # Copies of its sockets that gRPC does not know of (its fork handler closes the originals in the
        # child); a descriptor stays open until closed, so the copies need no name.
        for fd in map(int, os.listdir("/proc/self/fd")):
            with contextlib.suppress(OSError):  # the listing's own descriptor is closed by now
                if os.readlink(f"/proc/self/fd/{fd}").startswith("socket:"):
                    os.dup(fd)
        if os.fork() == 0:  # the child holds every socket the parent had; its own session, so not killed with the group
            os.setsid()
            devnull = os.open(os.devnull, os.O_WRONLY)
            for fd in (1, 2):  # the parent's log pipe closes with the parent: the orchestrator waits for that
                os.dup2(devnull, fd)
            time.sleep(self.linger)
            os._exit(0)
        os._exit(0)
