"""Java components under `cast run`: launched by the orchestrator, killed with SIGKILL, restarted."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import yaml
from cast_testing_pb2 import Counter

import cast
from cast.testing import RunningSystem
from cast.v1 import directory_pb2
from tests.interop.java_support import TEST_CLASSES, cast_run, java_classpath
from tests.interop.restart_support import PyWorker, holder_config, readable
from tests.interop.restart_support import eventually as wait_for


def components(run: RunningSystem) -> dict[str, directory_pb2.ComponentInfo]:
    return dict(run.components())


def locked_by_other(component: Any) -> bool:
    """Whether another component holds an ODR lock on "held"."""
    return not readable(component, "held")


def test_sigkilled_java_component_releases_locks_and_tasks_and_is_restarted(tmp_path: Path) -> None:
    java_classpath()  # fails the test if the Java build is missing
    config = holder_config(tmp_path, {
        "language": "java", "class": "cast.itest.Holder", "classpath": [str(TEST_CLASSES)],
    })
    run = cast_run(config, tmp_path / "runtime", tmp_path)
    py = None
    try:
        running = directory_pb2.COMPONENT_STATE_RUNNING
        first = wait_for(lambda: (c := components(run).get("holder")) and c.state == running and c)
        assert first, run.output()
        assert (first.language, first.kind, first.sessions) == ("java", "managed", 1)
        py = run.bind(PyWorker, "pyworker", "vision")
        assert wait_for(lambda: locked_by_other(py), 10)
        py.propose_task("python-task")
        assert not py.adopted_event.wait(1.0), "the Java task holds the only slot"

        os.kill(first.pid, signal.SIGKILL)

        assert py.adopted_event.wait(15), f"the killed component's task was not released\n{run.output()}"
        with py.lock("held", cast.LockMode.ODR, timeout=15):
            assert py.get("held", Counter).writer == "holder"
            # The orchestrator restarts the component: a new process, a second session, which waits for the lock.
            second = wait_for(lambda: (c := components(run)["holder"]).sessions == 2 and c.pid != first.pid and c)
            assert second, run.output()
        py.task_complete(py.adopted[0])
        # The restarted holder takes the lock and the task slot again.
        assert wait_for(lambda: locked_by_other(py), 30), run.output()
        assert wait_for(lambda: components(run)["holder"].state == directory_pb2.COMPONENT_STATE_RUNNING), run.output()
    finally:
        if py is not None:
            py._cast_close()
        run.stop()  # its exit status reports the crash; what matters here is what the crash left behind
    assert "holder crashed (exit code -9); restarting" in run.output()


def test_a_java_component_that_does_not_stop_leaves_a_thread_dump_in_its_log(tmp_path: Path) -> None:
    java_classpath()  # fails the test if the Java build is missing
    config = tmp_path / "stubborn.yaml"
    config.write_text(yaml.safe_dump({
        "system": "stubborn",
        "orchestrator": {"stop_timeout": 1},
        "subarchitectures": {"work": {"components": {"stubborn": {
            "language": "java", "class": "cast.itest.Stubborn", "classpath": [str(TEST_CLASSES)],
        }}}},
    }))
    run = cast_run(config, tmp_path / "runtime", tmp_path)
    run.wait_for_component("stubborn", "running", 30)
    assert run.stop() == 1, run.output()
    assert "stubborn did not stop within 1 s: killed (its threads' stacks are in its log)" in run.output()
    # SIGQUIT before the SIGKILL: the JVM's thread dump, with the thread stuck in Stubborn.stop.
    log = (tmp_path / "runtime" / "logs" / "stubborn.log").read_text()
    assert "Full thread dump" in log and "at cast.itest.Stubborn.stop(Stubborn.java" in log, log
