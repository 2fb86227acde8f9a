"""cast.testing, the kit for component authors: its systems, components, actors, collectors, waits and messages.

Most tests serve in the test's process (a tenth of a second each); those about processes start
`cast serve` or `cast run`, and those about the pytest plugin and cleanup after a failure or a
crash run pytest or Python as a process of their own and look for what it left behind.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from google.protobuf.wrappers_pb2 import Int64Value, StringValue

import cast
from cast.testing import LocalSystem, run_system, start_system, wait_for


class Counter(cast.UnmanagedComponent):
    """Counts to ``to`` in the entry ``count`` when an entry ``go`` appears; slow to start on purpose."""

    def configure(self, args: dict[str, Any]) -> None:
        self.last = int(args.get("to", 3))
        self.stopped = False

    def start(self) -> None:
        time.sleep(0.3)  # a watch registered late: run() must not return before it is
        self.on_change(cast.address_filter("go", cast.Operation.ADD), lambda change: self.count())

    def count(self) -> None:
        result = self.add("count", Int64Value(value=0))
        for n in range(1, self.last + 1):
            result = self.overwrite("count", Int64Value(value=n), expected_version=result.version)

    def stop(self) -> None:
        self.stopped = True


class Broken(cast.UnmanagedComponent):
    """Fails in start()."""

    def start(self) -> None:
        raise RuntimeError("no camera attached")


def alive(pid: int) -> bool:
    """Whether a process runs (a zombie no longer does)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


@pytest.fixture
def system() -> Any:
    with start_system(subarchitectures=["vision", "language"]) as made:
        yield made


# ------------------------------------------------------------------ components and actors


def test_a_running_component_is_handed_over_once_its_watches_are_registered(system: LocalSystem) -> None:
    running = system.run(Counter, "counter", "vision", args={"to": 3})
    system.act_as("camera", "vision").add("go", StringValue(value="now"))  # right away: start() slept first
    entry = system.wait_for_entry("vision", "count", Int64Value, Int64Value(value=3))
    assert entry.author == "counter"
    assert running.stop() == 0
    assert running.component.stopped and not running.running


def test_a_component_whose_hook_fails_ends_with_exit_code_1(system: LocalSystem) -> None:
    running = system.run(Broken, "broken", "vision")
    assert running.join() == 1


def test_a_bound_component_is_stepped_by_the_test(system: LocalSystem) -> None:
    counter = system.bind(Counter, "counter", "vision")
    counter.configure({"to": 2})
    counter.start()
    system.act_as("camera", "vision").add("go", StringValue(value="now"))
    system.wait_for_entry("vision", "count", Int64Value, lambda value: value.value == 2)
    assert counter.component_id == "counter" and not counter.privileged


def test_an_actor_writes_as_its_component_and_its_rights(system: LocalSystem) -> None:
    camera = system.act_as("camera", "vision")
    camera.add("image", StringValue(value="pixels"))
    assert system.assert_entry("vision", "image", StringValue).author == "camera"
    with pytest.raises(cast.PermissionDeniedError, match="'camera'"):
        camera.add("image", StringValue(value="pixels"), subarchitecture="language")
    system.act_as("boss", "vision", privileged=True).add("order", StringValue(value="go"), subarchitecture="language")


def test_an_actor_proposes_tasks_and_sees_the_decisions() -> None:
    config = {"system": "tasks", "subarchitectures": {"vision": {"task_manager": {"policy": "exclusive"}}}}
    with start_system(config) as system:
        planner = system.act_as("planner", "vision")
        first = planner.wait_for_decision(planner.propose_task("plan"))
        second = planner.wait_for_decision(planner.propose_task("plan again"))
        assert (first.state, second.state) == (cast.TaskState.ADOPTED, cast.TaskState.REJECTED)
        assert [t.task_id for t in planner.decisions] == [first.task_id, second.task_id]


def test_launch_environment_starts_a_component_process(system: LocalSystem, tmp_path: Path) -> None:
    (tmp_path / "greeter.py").write_text(textwrap.dedent("""
        from google.protobuf.wrappers_pb2 import StringValue
        import cast

        class Greeter(cast.UnmanagedComponent):
            def run(self) -> None:
                self.add("greeting", StringValue(value=self.component_id))
                self.request_stop()
    """))
    env = {**os.environ, **system.launch_environment("greeter", "language"), "PYTHONPATH": str(tmp_path)}
    done = subprocess.run([sys.executable, "-m", "cast.run", "greeter:Greeter"], env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    system.assert_entry("language", "greeting", StringValue, StringValue(value="greeter"))


def test_the_runners_started_hook_comes_once_before_run_and_when_the_lifecycle_ends_early(
    system: LocalSystem,
) -> None:
    from cast.client.grpc_transport import GrpcTransport
    from cast.client.runner import run_component
    from cast.core.records import Identity

    seen: list[str] = []

    class Ordered(cast.UnmanagedComponent):
        def start(self) -> None:
            seen.append("start")

        def run(self) -> None:
            seen.append("run")
            self.request_stop()

    def transport(component_id: str) -> GrpcTransport:
        return GrpcTransport(system.endpoint, system.token(component_id, "vision"), Identity(component_id, "vision"))

    assert run_component(Ordered(), transport("ordered"), {}, handle_signals=False,
                         started=lambda: seen.append("started")) == 0
    assert seen == ["start", "started", "run"]
    seen.clear()
    assert run_component(Broken(), transport("broken"), {}, handle_signals=False,
                         started=lambda: seen.append("started")) == 1
    assert seen == ["started"]


# ------------------------------------------------------------------ collecting and waiting


def test_collected_changes_come_in_order_and_a_timeout_lists_them(system: LocalSystem) -> None:
    changes = system.collect_changes(cast.address_filter("count", subarchitecture="vision", include_entry=True))
    running = system.run(Counter, "counter", "vision", args={"to": 2})
    system.act_as("camera", "vision").add("go", StringValue(value="now"))
    seen = changes.wait_for_count(3)
    assert [c.operation for c in seen] == [cast.Operation.ADD, cast.Operation.OVERWRITE, cast.Operation.OVERWRITE]
    assert [c.entry(Int64Value).value.value for c in seen] == [0, 1, 2]
    with pytest.raises(AssertionError) as failed:
        changes.wait_for_count(4, timeout=0.2)
    assert "expected 4 changes, got 3 changes" in str(failed.value)
    assert "OVERWRITE vision/count by counter (revision 4): google.protobuf.Int64Value {value: 2}" in str(failed.value)
    with pytest.raises(AssertionError, match="waiting for a delete"):
        changes.wait_for_change(lambda c: c.operation == cast.Operation.DELETE, 0.2, "a delete")
    assert running.stop() == 0


def test_a_failed_entry_assertion_says_what_the_entry_holds(system: LocalSystem) -> None:
    system.act_as("counter", "vision").add("count", Int64Value(value=2))
    with pytest.raises(AssertionError) as failed:
        system.assert_entry("vision", "count", Int64Value, Int64Value(value=3))
    assert "entry 'count' in subarchitecture 'vision' holds google.protobuf.Int64Value {value: 2}" in str(failed.value)
    assert "by counter), expected google.protobuf.Int64Value {value: 3}" in str(failed.value)
    with pytest.raises(AssertionError, match=r"no entry 'counts' .*entries there: count \(google.protobuf.Int64"):
        system.assert_entry("vision", "counts", Int64Value)
    with pytest.raises(AssertionError, match="has type google.protobuf.Int64Value, not google.protobuf.StringValue"):
        system.assert_entry("vision", "count", StringValue)

    def even(value: Int64Value) -> bool:
        return value.value % 2 == 1

    with pytest.raises(AssertionError, match=r"which even\(\) refused"):
        system.assert_entry("vision", "count", Int64Value, even)
    with pytest.raises(AssertionError) as timed_out:
        system.wait_for_entry("vision", "count", Int64Value, Int64Value(value=3), timeout=0.2)
    assert str(timed_out.value).startswith("timed out after 0.2 s waiting for entry 'count' in subarchitecture "
                                           "'vision': entry 'count' in subarchitecture 'vision' holds")


def test_wait_for_returns_the_first_true_answer_and_says_what_it_saw_last() -> None:
    answers = iter([0, [], "yes"])
    assert wait_for(lambda: next(answers), 5) == "yes"
    greetings = ["hello"]
    with pytest.raises(AssertionError, match=r"^timed out after 0.05 s waiting for a goodbye; the condition last "
                                             r"returned \[\]$"):
        wait_for(lambda: [g for g in greetings if g.startswith("bye")], 0.05, "a goodbye")

    def three_greetings() -> list[str]:
        assert len(greetings) == 3, f"{len(greetings)} greeting(s): {greetings}"
        return greetings

    with pytest.raises(AssertionError, match=r"^timed out after 0.05 s waiting for three_greetings\(\): 1 "
                                             r"greeting\(s\): \['hello'\]"):
        wait_for(three_greetings, 0.05)


# ------------------------------------------------------------------ systems


def test_a_system_from_a_yaml_file_with_variables_or_a_dict(tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump({"system": "robot", "variables": {"SA": "vision"},
                                    "subarchitectures": {"${SA}": {}, "motor": {}}}))
    with start_system(path, sets={"SA": "eyes"}) as system:
        assert (system.name, system.subarchitectures) == ("robot", ["eyes", "motor"])
    with start_system({"system": "small", "subarchitectures": {"arm": {}}}) as system:
        assert system.subarchitectures == ["arm"]
        with pytest.raises(cast.InvalidArgumentError, match="no subarchitecture 'vision' in system 'small'"):
            system.act_as("camera", "vision")
    with pytest.raises(cast.InvalidArgumentError, match="has errors:\n.*subarchitectures"):
        start_system({"system": "bad", "subarchitecture": {"arm": {}}})
    with pytest.raises(cast.NotFoundError, match="no configuration file"):
        start_system(tmp_path / "missing.yaml")


def test_a_served_process_restarts_empty_and_leaves_nothing_when_closed() -> None:
    system = start_system(subarchitectures=["vision"], process=True)
    server = system._server.process  # type: ignore[attr-defined]
    directory = system.directory
    camera = system.act_as("camera", "vision")
    camera.add("image", StringValue(value="before"))
    system.restart()
    assert server.poll() is not None and system._server.process.pid != server.pid  # type: ignore[attr-defined]
    # The actor reconnects by itself; the new server holds nothing of the old one.
    wait_for(lambda: _add_again(camera), 20, "the actor writing to the restarted server")
    system.assert_entry("vision", "image", StringValue, StringValue(value="after"))
    assert "listening on" in system.output()
    restarted = system._server.process  # type: ignore[attr-defined]
    assert system.close() == 0
    assert not alive(restarted.pid) and not directory.exists()


def _add_again(camera: cast.ManagedComponent) -> bool:
    try:
        camera.add("image", StringValue(value="after"))
    except cast.UnavailableError:
        return False
    return True


def test_run_system_runs_the_configuration_and_its_tools(tmp_path: Path) -> None:
    (tmp_path / "greeter.py").write_text(textwrap.dedent("""
        from google.protobuf.wrappers_pb2 import StringValue
        import cast

        class Greeter(cast.UnmanagedComponent):
            def run(self) -> None:
                self.add("greeting", StringValue(value="hello"))
                print("greeted", flush=True)
                self.wait_for_stop()
    """))
    config = tmp_path / "system.yaml"
    config.write_text(yaml.safe_dump({"system": "greeting", "python_path": ["."], "subarchitectures": {
        "language": {"components": {"greeter": {"language": "python", "class": "greeter:Greeter"}}}}}))
    system = run_system(config)
    system.wait_for_line("greeted")
    system.wait_for_entry("language", "greeting", StringValue, StringValue(value="hello"))
    assert system.components()["greeter"].kind == "unmanaged"
    assert "greeting" in system.cli("ls", "language").stdout
    process = system._server.process  # type: ignore[attr-defined]
    assert system.stop(signal.SIGINT) == 0
    assert not alive(process.pid) and not system.directory.exists()


# ------------------------------------------------------------------ the pytest plugin, failures and crashes

PLUGIN_TESTS = '''
import os
from pathlib import Path

import pytest
from google.protobuf.wrappers_pb2 import Int64Value

pytestmark = pytest.mark.cast_system(subarchitectures=["arm"])


def test_passes(cast_system):
    assert cast_system.subarchitectures == ["arm"]


@pytest.mark.cast_system(subarchitectures=["arm"], process=True)
def test_fails(cast_system):
    Path("left.txt").write_text(f"{cast_system._server.process.pid} {cast_system.directory}")
    cast_system.act_as("gripper", "arm").add("grip", Int64Value(value=1))
    cast_system.assert_entry("arm", "grip", Int64Value, Int64Value(value=2))
'''


def test_the_pytest_plugin_reports_a_failure_with_the_server_output_and_cleans_up(tmp_path: Path) -> None:
    (tmp_path / "test_plugin.py").write_text(PLUGIN_TESTS)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CAST_", "PYTEST_"))}
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_plugin.py"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "1 failed, 1 passed" in done.stdout, done.stdout
    assert "entry 'grip' in subarchitecture 'arm' holds google.protobuf.Int64Value {value: 1} (version" in done.stdout
    assert "cast system 'test' at 127.0.0.1:" in done.stdout and "listening on 127.0.0.1:" in done.stdout
    pid, directory = (tmp_path / "left.txt").read_text().split()
    assert not alive(int(pid)), "the failed test's server is still running"
    assert not Path(directory).exists(), "the failed test's directory is still there"


CRASH = '''
import os, signal, sys
from cast.testing import run_system, start_system

served = start_system(subarchitectures=["arm"], process=True)
config = os.path.join(sys.argv[1], "run.yaml")
with open(config, "w") as f:
    f.write("system: crash\\nsubarchitectures:\\n  arm: {}\\n")
run = run_system(config)
print(served._server.process.pid, run._server.process.pid, flush=True)
os.kill(os.getpid(), signal.SIGKILL)
'''


def test_a_killed_test_process_leaves_no_server_behind(tmp_path: Path) -> None:
    # A process killed with SIGKILL cannot remove its systems' directories: they go under tmp_path, not /tmp.
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", CRASH, str(tmp_path)], capture_output=True, text=True, timeout=120,
                          env=env)
    assert done.returncode == -signal.SIGKILL, done.stderr
    pids = [int(pid) for pid in done.stdout.split()]
    assert len(pids) == 2, done.stdout + done.stderr
    wait_for(lambda: not any(alive(pid) for pid in pids), 30, "cast serve and cast run to end with the test process")
    assert len(list(tmp_path.glob("cast-testing-*"))) == 2, "the killed process's two systems left their directories"
