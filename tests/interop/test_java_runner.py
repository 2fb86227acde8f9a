"""The Java runner: launch contract, exit status, signals, sessions; a SIGKILLed component's locks and tasks."""

from __future__ import annotations

import os
import subprocess
import threading
from pathlib import Path
from typing import Any

import pytest
from cast_testing_pb2 import Counter

import cast
from cast.v1 import directory_pb2
from tests.conftest import wait_for
from tests.interop.java_support import RUNNER, JavaComponent, counter_json, java_classpath


def run_java(env: dict[str, str], *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["java", "-cp", java_classpath(), RUNNER, *args], env=env, capture_output=True, text=True, timeout=timeout
    )


def test_missing_launch_environment_exits_2_naming_the_variables() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    env["CAST_COMPONENT_ID"] = "x"
    r = run_java(env, "cast.itest.Driven")
    assert r.returncode == 2, r.stderr
    assert "missing launch environment: CAST_ENDPOINT, CAST_SUBARCHITECTURE, CAST_TOKEN or CAST_TOKEN_FILE;" in r.stderr


def test_cast_token_file_alone_is_the_token_and_an_empty_file_exits_2(server: Any, tmp_path: Path) -> None:
    # The launch contract of `cast export --to kubernetes`: CAST_TOKEN_FILE, no CAST_TOKEN (ArgsAndContractTest has
    # the rules; Python and C++: tests/integration/test_system.py, test_cpp_session.py).
    token = tmp_path / "jfiled.token"
    env = server.env("jfiled", "vision", token_file=token)
    jc = JavaComponent(env)
    try:
        jc.ready()
        jc.ok("add", id="from-file", type="cast.testing.Counter", value=counter_json("jfiled", 7))
        assert jc.quit() == 0, jc.output()
    finally:
        jc.close()
    reader = server.connect("reader", "vision")
    try:
        assert reader.get("from-file", Counter).writer == "jfiled"
    finally:
        reader._cast_close()
    token.write_text("")
    r = run_java(env, "cast.itest.Driven")
    assert r.returncode == 2, r.stderr
    assert (f"CAST_TOKEN_FILE names {token}, which is empty: point it at a token file (`cast run` renews one per "
            "component), or unset it") in r.stderr


def test_bad_class_and_usage_exit_2(server: Any) -> None:
    env = server.env("j", "vision")
    r = run_java(env, "no.such.Component")
    assert r.returncode == 2 and "not on the class path" in r.stderr, r.stderr
    r = run_java(env, "java.lang.String")
    assert r.returncode == 2 and "must extend cast.client.UnmanagedComponent" in r.stderr, r.stderr
    r = run_java(env)
    assert r.returncode == 2 and "usage:" in r.stderr
    bad_args = dict(env, CAST_ARGS="[1, 2]")
    r = run_java(bad_args, "cast.itest.Driven")
    assert r.returncode == 2 and "CAST_ARGS" in r.stderr, r.stderr


def test_a_bad_token_exits_2(server: Any) -> None:
    env = dict(server.env("j", "vision"), CAST_TOKEN="forged.token")
    r = run_java(env, "cast.itest.Driven")
    assert r.returncode == 2, r.stderr
    assert "cannot join the system" in r.stderr


@pytest.mark.parametrize("hook", ["configure", "start", "run", "stop"])
def test_a_failing_hook_exits_1_and_stop_is_still_called(server: Any, hook: str) -> None:
    env = server.env("jfail", "vision", args={"fail": hook})
    proc = subprocess.Popen(
        ["java", "-cp", java_classpath(), RUNNER, "cast.itest.Failing"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    if hook == "stop":
        # Runs until asked to stop; the failure comes from stop() itself.
        assert wait_for(lambda: server.components().get("jfail", directory_pb2.ComponentInfo()).state
                        == directory_pb2.COMPONENT_STATE_RUNNING, 30)
        proc.terminate()
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert f"failing in {hook} on purpose" in err
    assert out.count("stop called") == 1


def test_sigterm_calls_stop_exits_0_and_ends_the_session(server: Any) -> None:
    jc = JavaComponent(server.env("jterm", "vision"))
    try:
        jc.ready()
        assert wait_for(lambda: server.components()["jterm"].state == directory_pb2.COMPONENT_STATE_RUNNING)
        info = server.components()["jterm"]
        assert (info.language, info.kind, info.pid) == ("java", "managed", jc.proc.pid)
        jc.ok("add", id="x", type="cast.testing.Counter", value=counter_json("jterm", 1))
        jc.ok("lock", id="x", mode="ODR")
        jc.terminate()
        jc.wait_event("stopping")
        assert jc.wait() == 0, jc.output()
        assert server.components()["jterm"].state == directory_pb2.COMPONENT_STATE_DISCONNECTED
        py = server.connect("pyafter", "vision")
        try:
            assert py.try_lock("x", cast.LockMode.ODR), "the lock went with the session"
        finally:
            py._cast_close()
    finally:
        jc.close()


class PyWorker(cast.ManagedComponent):
    """A Python managed component that records its adopted tasks."""

    def __init__(self) -> None:
        super().__init__()
        self.adopted: list[str] = []
        self.adopted_event = threading.Event()

    def task_adopted(self, task: cast.Task) -> None:
        self.adopted.append(task.name)
        self.adopted_event.set()


def test_sigkill_releases_the_java_components_locks_and_tasks(server_factory: Any) -> None:
    server = server_factory({"system": "kill", "subarchitectures": {
        "vision": {"task_manager": {"policy": "fifo", "max_concurrent": 1}}}})
    jc = JavaComponent(server.env("jvictim", "vision"))
    py = server.connect("pysurvivor", "vision", cls=PyWorker)
    try:
        jc.ready()
        jc.ok("add", id="shared", type="cast.testing.Counter", value=counter_json("jvictim", 1))
        jc.ok("lock", id="shared", mode="ODR")
        jc.ok("propose", name="java-task")
        assert jc.wait_event("adopted")["name"] == "java-task"
        py.propose_task("python-task")
        assert not py.adopted_event.wait(1.0), "the Java task holds the only slot"
        with pytest.raises(cast.LockedError):
            py.get("shared", Counter)

        jc.proc.kill()  # SIGKILL: no stop(), no goodbye; the server sees the session's streams break
        jc.proc.wait(10)

        assert py.adopted_event.wait(15), "the killed component's task was not released"
        assert py.adopted == ["python-task"]
        with py.lock("shared", cast.LockMode.ODR, timeout=15):
            assert py.get("shared", Counter).writer == "jvictim"
        assert wait_for(lambda: server.components()["jvictim"].state == directory_pb2.COMPONENT_STATE_DISCONNECTED)
    finally:
        py._cast_close()
        jc.close()
