"""C++ component sessions: the runner's launch contract and exit codes, signals, and what a SIGKILL leaves behind."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Counter

import cast
from cast.v1 import directory_pb2, task_manager_pb2, task_manager_pb2_grpc
from tests.conftest import components
from tests.interop.cpp_support import CppProbe, CppProcess, cast_run, cpp_executable
from tests.interop.restart_support import PyWorker, holder_config, readable
from tests.interop.restart_support import eventually as wait_for


def live_tasks(endpoint: str, token: str, sa: str) -> list[task_manager_pb2.Task]:
    with grpc.insecure_channel(endpoint) as channel:
        stub = task_manager_pb2_grpc.TaskManagerStub(channel)
        resp = stub.ListTasks(task_manager_pb2.ListTasksRequest(subarchitecture=sa),
                              metadata=(("authorization", f"Bearer {token}"),))
    return list(resp.tasks)


# ------------------------------------------------------------------ SIGKILL, server side


def test_sigkilled_cpp_component_releases_its_locks_and_tasks(server_factory: Any) -> None:
    handle = server_factory({"system": "kill", "subarchitectures": {
        "vision": {"task_manager": {"policy": "fifo", "max_concurrent": 1}}}})
    tool = handle.token("tool", "vision")
    c = CppProbe(handle.env("cvictim", "vision"))
    py = handle.connect("pysurvivor", "vision", cls=PyWorker)
    try:
        c.ready()
        c.ok("add", "Counter", "held", "-", {"writer": "cvictim", "value": "1"})
        assert c.ok("lock", "held", "ODR", "-", "-") == {"depth": 1}
        assert c.ok("lock", "held", "ODR", "-", "-") == {"depth": 2}  # two levels: all go with the session
        assert c.ok("propose", "running", 0)["state"] in ("WAITING", "ADOPTED")
        c.ok("propose", "queued", 0)
        decided = c.ok("decisions", 1, 10000)["decisions"]
        assert [d["name"] for d in decided] == ["running"]
        assert not readable(py, "held")
        assert sorted(t.name for t in live_tasks(handle.endpoint, tool, "vision")) == ["queued", "running"]
        py.propose_task("python-task")  # waits behind the C++ tasks (fifo, one at a time)
        assert not py.adopted_event.wait(0.5)

        c.kill()  # no stop(), no unlock, no goodbye: the server sees the session end

        assert wait_for(lambda: readable(py, "held"), 10), "the ODR lock was not released"
        assert py.try_lock("held", cast.LockMode.ODR)
        py.unlock("held")
        assert py.adopted_event.wait(10), "the slot of the killed component's task was not freed"
        assert [t.name for t in py.adopted] == ["python-task"]
        assert [t.name for t in live_tasks(handle.endpoint, tool, "vision")] == ["python-task"]
        info = components(handle.endpoint, tool)["cvictim"]
        assert info.state == directory_pb2.COMPONENT_STATE_DISCONNECTED
    finally:
        py._cast_close()
        c.close()


# ------------------------------------------------------------------ the runner


def run_once(env: dict[str, str], name: str = "cast_probe", timeout: float = 30.0) -> tuple[int, str]:
    proc = CppProcess(name, env, stdin=True)
    try:
        status = proc.wait(timeout)
        time.sleep(0.1)  # let the reader threads collect the last lines
        return status, proc.output()
    finally:
        proc.close()


def test_missing_launch_environment_exits_2_naming_every_variable() -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    env["CAST_COMPONENT_ID"] = "lonely"
    status, out = run_once(env)
    assert status == 2
    assert "missing launch environment: CAST_ENDPOINT, CAST_SUBARCHITECTURE, CAST_TOKEN or CAST_TOKEN_FILE;" in out, out


def test_cast_token_file_alone_is_the_token_and_a_bad_file_exits_2(server: Any, tmp_path: Path) -> None:
    # The launch contract of `cast export --to kubernetes`: CAST_TOKEN_FILE, no CAST_TOKEN (runner_test.cc has
    # the rules; Python and Java: tests/integration/test_system.py, test_java_runner.py).
    token = tmp_path / "cfiled.token"
    env = server.env("cfiled", "vision", token_file=token)
    c = CppProbe(env)
    try:
        c.ready()
        assert c.ok("whoami") == {"id": "cfiled", "sa": "vision", "privileged": False}
        c.ok("add", "Counter", "from-file", "-", {"writer": "cfiled", "value": "7"})
        assert c.quit() == 0, c.output()
    finally:
        c.close()
    reader = server.connect("reader", "vision")
    try:
        assert reader.get("from-file", Counter).value == 7
    finally:
        reader._cast_close()
    token.write_text("")
    status, out = run_once(env)
    assert status == 2, out
    assert (f"CAST_TOKEN_FILE names {token}, which is empty: point it at a token file (`cast run` renews one per "
            "component), or unset it") in out, out
    token.unlink()
    status, out = run_once(env)
    assert status == 2 and f"CAST_TOKEN_FILE names {token}, which cannot be read" in out, out


def test_bad_args_exit_2(server: Any) -> None:
    env = server.env("cargs", "vision")
    env["CAST_ARGS"] = "[1, 2]"
    status, out = run_once(env)
    assert status == 2 and "CAST_ARGS must be a JSON object" in out, out
    env["CAST_ARGS"] = "{not json"
    status, out = run_once(env)
    assert status == 2 and "CAST_ARGS is not valid JSON" in out, out


def test_refused_token_and_unreachable_server_exit_2(server: Any) -> None:
    env = server.env("ctoken", "vision")
    env["CAST_TOKEN"] = "forged.token"
    status, out = run_once(env)
    assert status == 2, out
    env = server.env("cnowhere", "vision")
    env["CAST_ENDPOINT"] = "127.0.0.1:1"
    env["CAST_CONNECT_WINDOW_S"] = "1.5"  # nobody ever answers: it asks for its connect window (20 s unless set)
    status, out = run_once(env, timeout=60)
    assert status == 2 and "no CAST system answered at 127.0.0.1:1 within 1.5 s" in out, out
    assert "server unavailable" in out, out


def test_a_token_for_another_component_exits_2_naming_both(server: Any) -> None:
    # The server says whom it verified the token for when the component registers;
    # a launch environment that says otherwise is refused before any hook runs.
    env = server.env("cwriter", "vision")
    env["CAST_TOKEN"] = server.token("cother", "vision")
    status, out = run_once(env)
    assert status == 2, out
    assert "started as 'cwriter' in subarchitecture 'vision'" in out, out
    assert "verified its token as 'cother' in subarchitecture 'vision'" in out, out
    assert '"ready"' not in out, "start() ran under another component's identity"
    env["CAST_TOKEN"] = server.token("cwriter", "language")
    status, out = run_once(env)
    assert status == 2, out
    assert "verified its token as 'cwriter' in subarchitecture 'language'" in out, out
    # Registering is how it learnt the verified identity, so the server saw a session
    # under the token's identity; it never got further than STARTING (it ends with its
    # heartbeat stream, or at lease expiry if the refusal came before that stream opened).
    tool = server.token("tool", "vision")
    for component_id in ("cother", "cwriter"):
        info = components(server.endpoint, tool).get(component_id)
        assert info is None or info.state in (directory_pb2.COMPONENT_STATE_STARTING,
                                              directory_pb2.COMPONENT_STATE_DISCONNECTED), info


def test_a_failing_hook_exits_1(server: Any) -> None:
    env = server.env("cfail", "vision", args={"mode": "nonsense"})
    status, out = run_once(env, "cast_test_fidelity")
    assert status == 1
    assert "args must be" in out, out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_calls_stop_and_exits_0(server: Any, sig: signal.Signals) -> None:
    # The tasker works on adopted tasks off the dispatcher; stop() joins its workers.
    proc = CppProcess("cast_test_tasker", server.env("csig", "vision", args={"tasks": 2, "work_ms": 60000}))
    try:
        lines = [proc.next_json(30) for _ in range(4)]  # 2 proposed, 2 adopted (policy always)
        assert sum(1 for x in lines if "adopted" in x) == 2, lines
        started = time.monotonic()
        proc.proc.send_signal(sig)
        assert proc.wait(15) == 0, proc.output()
        assert time.monotonic() - started < 10, "stop must not wait for the work to finish"
        tool = server.token("tool", "vision")
        # A clean stop ends the session: the tasks it left adopted are released.
        assert wait_for(lambda: not live_tasks(server.endpoint, tool, "vision"), 10)
    finally:
        proc.close()


def test_help_needs_no_environment() -> None:
    import subprocess

    out = subprocess.run([str(cpp_executable("cast_probe")), "--help"], capture_output=True, text=True, timeout=10)
    assert out.returncode == 0 and "CAST_ENDPOINT" in out.stdout


# ------------------------------------------------------------------ under the orchestrator


def test_sigkilled_cpp_component_is_restarted_by_the_orchestrator(tmp_path: Path) -> None:
    cpp_executable("cast_test_tasker")  # fails the test if the C++ build is missing
    config = holder_config(tmp_path, {
        "language": "cpp", "run": "cast_test_tasker",
        "args": {"tasks": 1, "work_ms": 600000, "hold": "held", "prefix": "cpp-"},
    })
    run = cast_run(config, tmp_path / "runtime")
    py = None
    try:
        tool = run.token("tool", "vision")

        def holder_running(sessions: int) -> Any:
            info = components(run.endpoint, tool).get("holder")
            ok = info and info.state == directory_pb2.COMPONENT_STATE_RUNNING and info.sessions == sessions
            return info if ok else None

        first = wait_for(lambda: holder_running(1), 60)
        assert first, run.output()
        assert (first.language, first.kind) == ("cpp", "managed")
        py = run.bind(PyWorker, "pyworker", "vision")
        assert wait_for(lambda: not readable(py, "held"), 10), "the C++ component holds its lock"
        assert wait_for(lambda: [t.name for t in live_tasks(run.endpoint, tool, "vision")] == ["cpp-0"], 10)
        py.propose_task("python-task")  # queued behind the C++ task
        assert not py.adopted_event.wait(0.5)
        # A blocking Python lock waits for the C++ one; it gets it when the session ends,
        # before the restarted component can lock again.
        got: list[cast.LockGuard] = []
        waiter = threading.Thread(target=lambda: got.append(py.lock("held", cast.LockMode.ODR, timeout=30)))
        waiter.start()

        os.kill(first.pid, signal.SIGKILL)

        waiter.join(30)
        assert got, "the killed component's lock was not released"
        assert py.adopted_event.wait(10), "the killed component's task was not released"
        assert [t.name for t in py.adopted] == ["python-task"]
        # Restarted at once; its start() waits for the lock Python now holds.
        second = wait_for(lambda: (i := components(run.endpoint, tool).get("holder")) and i.sessions == 2 and i, 30)
        assert second, f"not restarted\n{run.output()}"
        assert second.pid != first.pid
        got[0].unlock()
        assert wait_for(lambda: holder_running(2), 30), f"the restarted component did not start\n{run.output()}"
        assert wait_for(lambda: not readable(py, "held"), 10), "the restarted component takes its lock again"
        # It proposes again, behind the Python task that now runs.
        assert wait_for(lambda: sorted(t.name for t in live_tasks(run.endpoint, tool, "vision"))
                        == ["cpp-0", "python-task"], 10)
    finally:
        if py is not None:
            py._cast_close()
        run.stop()
    # Nothing is left behind: the restarted C++ process ended with the system.
    assert wait_for(lambda: not Path(f"/proc/{second.pid}").exists(), 10)
