"""Supervision: restarts by policy (locks and tasks of the crashed process released), clean shutdown, no orphans."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil

from cast.core.records import Identity
from cast.orchestrator.supervisor import Phase
from tests.orchestrator.conftest import CAST, COMPONENTS, Embedded, start_cast_run, wait_for, write_config
from tests.terminal import Terminal


def gone(pid: int) -> bool:
    """The process no longer exists (or is a zombie waiting for its parent)."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def test_crashed_component_is_restarted_and_its_lock_and_task_released(
    tmp_path: Path, embedded: Callable[..., Embedded]
) -> None:
    marker = tmp_path / "crashed-once"
    cfg = write_config(tmp_path / "crash.yaml", {
        "system": "crash",
        "subarchitectures": {
            "work": {
                "task_manager": {"policy": "exclusive"},
                "components": {"crasher": {
                    "kind": "managed", "class": "orch_components:Crasher", "args": {"marker": str(marker)},
                    "restart": {"policy": "on-failure", "backoff": 0.05},
                }},
            },
            "other": {"components": {"checker": {
                "class": "orch_components:Checker", "args": {"target_sa": "work", "marker": str(marker)},
                "privileged": True,  # it writes the other SA's entry
            }}},
        },
    })
    run = embedded(cfg)
    host = run.system("work").host
    who = Identity("test", "work")
    # The restarted crasher's task is adopted although the exclusive TM had adopted the dead one's.
    wait_for(lambda: host.exists(who, "work", "adopted-after-restart"), what="a task adopted after the restart")
    # Another component could take the lock the crashed process held.
    wait_for(lambda: host.exists(who, "work", "held") and host.get(who, "work", "held").author == "checker",
             what="the checker to overwrite the formerly locked entry")
    tasks = run.system("work").tasks
    assert tasks.counters["work"]["retracted"] >= 1  # the dead process's task
    assert all(t.name != "doomed" for t in tasks.tasks("work"))
    sup = run.orchestrator.supervisor
    assert sup is not None
    crasher = sup.components["crasher"]
    assert (crasher.restarts, crasher.crashes, crasher.phase) == (1, [3], Phase.RUNNING)
    info = next(c for c in run.system("work").sessions.components() if c.id == "crasher")
    assert info.sessions == 2 and info.session_id
    result = run.stop()
    assert "crasher crashed (exit code 3); restarting" in run.text()
    assert result.failures == ["crasher crashed 1 time(s) (exit codes 3)"]
    assert result.exit_code == 1


def test_restart_policies_never_and_max_restarts(tmp_path: Path, embedded: Callable[..., Embedded]) -> None:
    cfg = write_config(tmp_path / "failing.yaml", {
        "subarchitectures": {"work": {"components": {
            "once": {"class": "orch_components:Failing", "restart": "never"},
            "thrice": {"class": "orch_components:Failing",
                       "restart": {"policy": "on-failure", "max_restarts": 2, "backoff": 0.01}},
            "steady": {"class": "orch_components:Producer"},
        }}},
    })
    run = embedded(cfg, wait=False)
    sup = wait_for(lambda: run.orchestrator.supervisor, what="the supervisor")
    wait_for(lambda: sup.components["once"].phase is Phase.FAILED and sup.components["thrice"].phase is Phase.FAILED,
             what="both failing components to give up")
    assert (sup.components["once"].restarts, sup.components["once"].crashes) == (0, [1])
    assert (sup.components["thrice"].restarts, sup.components["thrice"].crashes) == (2, [1, 1, 1])
    result = run.stop()
    assert "thrice crashed (exit code 1); not restarted after 2 restarts" in run.text()
    assert "once crashed (exit code 1); not restarted (restart: never)" in run.text()
    assert result.exit_code == 1
    assert sup.components["steady"].stop_code == 0


def test_sigterm_stops_components_in_reverse_order_and_leaves_no_process(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "tidy.yaml", {
        "system": "tidy",
        "subarchitectures": {"work": {"components": {
            "first": {"class": "orch_components:Recorder"},
            "spawner": {"class": "orch_components:Spawner"},
            "last": {"class": "orch_components:Recorder"},
        }}},
    })
    run = start_cast_run(tmp_path, cfg)
    pids = [c["pid"] for c in run.cli_json("components")]
    child = wait_for(lambda: _child_pid(run), what="the spawner's child")
    assert all(not gone(p) for p in [*pids, child])
    assert run.stop(signal.SIGTERM) == 0, run.output()
    out = run.output()
    assert out.index("last | stop() called") < out.index("first | stop() called")
    wait_for(lambda: all(gone(p) for p in [*pids, child]), timeout=10, what="every process to be gone")
    assert not (run.runtime_dir / "system.json").exists() and not (run.runtime_dir / "secret").exists()
    assert (run.runtime_dir / "logs" / "first.log").read_text().strip().endswith("stop() called")


def test_closing_its_terminal_stops_the_run_in_order_and_the_summary_is_still_written(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "hangup.yaml", {
        "system": "hangup",
        "subarchitectures": {"work": {"components": {
            "first": {"class": "orch_components:Recorder"},
            "last": {"class": "orch_components:Recorder"},
        }}},
    })
    runtime, summary = tmp_path / "rt", tmp_path / "summary.json"
    # Typed into an interactive shell in a window, with the live status view on, as a user runs it. Closing
    # the window sends `cast run` SIGHUP twice: the kernel's to the foreground job and the shell's to its jobs.
    window = Terminal(["/bin/bash", "--norc", "--noprofile", "-i"], cwd=tmp_path)
    try:
        window.type(f"{CAST} run {cfg} --runtime-dir {runtime} --summary-json {summary}")
        window.wait_for("components started in")
        pid = json.loads((runtime / "system.json").read_text())["pid"]
        window.close()
        wait_for(lambda: gone(pid), timeout=60, what="`cast run` to end")
    finally:
        window.end()
    data = json.loads(summary.read_text())
    assert data["failures"] == [], data
    assert {c["id"]: c["session"] for c in data["components"]} == {"first": "disconnected", "last": "disconnected"}
    for name in ("first", "last"):
        assert (runtime / "logs" / f"{name}.log").read_text().strip().endswith("stop() called")
    assert not (runtime / "system.json").exists()


def _child_pid(run: Any) -> int:
    out = run.cli("get", "work", "child-pid", "--json", check=False)
    # An Int64Value renders as its value, a string (protobuf JSON for 64-bit numbers).
    return int(json.loads(out.stdout)["value"]) if out.returncode == 0 else 0


def test_component_that_ignores_stop_is_killed_and_fails_the_run(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "stubborn.yaml", {
        "orchestrator": {"stop_timeout": 1},
        "subarchitectures": {"work": {"components": {"stubborn": {"class": "orch_components:Stubborn"}}}},
    })
    out = subprocess.run([CAST, "run", str(cfg), "--for", "0.5", "--no-status", "--runtime-dir", str(tmp_path / "rt")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stdout + out.stderr
    assert "stubborn did not stop within 1 s: killed (its threads' stacks are in its log)" in out.stdout
    assert "failed: stubborn exited with code -9 when stopped (killed)" in out.stdout
    # Asked with SIGQUIT before the SIGKILL, the runner wrote where it was stuck: Stubborn.stop's sleep.
    log = (tmp_path / "rt" / "logs" / "stubborn.log").read_text()
    assert re.search(r'orch_components\.py", line \d+ in stop', log), log
    assert "Thread 0x" in log, log


def test_killing_the_orchestrator_takes_its_components_along(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "orphans.yaml", {
        "subarchitectures": {"work": {"components": {"a": {"class": "orch_components:Recorder"},
                                                     "b": {"class": "orch_components:Recorder"}}}},
    })
    run = start_cast_run(tmp_path, cfg)
    pids = [c["pid"] for c in run.cli_json("components")]
    assert run.stop(signal.SIGKILL) == -signal.SIGKILL
    wait_for(lambda: all(gone(p) for p in pids), timeout=30, what="the components to follow their orchestrator")


def test_for_seconds_exits_non_zero_when_a_component_failed(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "bad.yaml", {
        "subarchitectures": {"work": {"components": {
            "broken": {"class": "orch_components:Failing", "restart": "never"},
            "fine": {"class": "orch_components:Producer"},
        }}},
    })
    out = subprocess.run([CAST, "run", str(cfg), "--for", "1", "--no-status", "--runtime-dir", str(tmp_path / "rt")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stdout + out.stderr
    assert "failed: broken crashed 1 time(s) (exit codes 1)" in out.stdout
    assert "RuntimeError: broken on purpose" in (tmp_path / "rt" / "logs" / "broken.log").read_text()


def test_in_process_component_runs_inside_the_server(tmp_path: Path, embedded: Callable[..., Embedded]) -> None:
    cfg = write_config(tmp_path / "inproc.yaml", {
        "subarchitectures": {"work": {"components": {
            "inside": {"class": "orch_components:Producer", "in_process": True, "args": {"count": 2}},
            "outside": {"kind": "managed", "class": "orch_components:Worker", "args": {"source_sa": "work"}},
        }}},
    })
    run = embedded(cfg)
    host = run.system("work").host
    who = Identity("test", "work")
    wait_for(lambda: host.exists(who, "work", "result-1"), what="the worker's results for the in-process items")
    infos = {c.id: c for c in run.system("work").sessions.components()}
    assert infos["inside"].pid == os.getpid()  # the server's (here: the test's) process
    assert infos["outside"].pid != os.getpid()
    assert run.stop().exit_code == 0


def test_servers_split_subarchitectures_and_route_components(
    tmp_path: Path, embedded: Callable[..., Embedded]
) -> None:
    cfg = write_config(tmp_path / "two-servers.yaml", {
        "system": "split",
        "subarchitectures": {
            "vision": {"components": {
                "worker": {"kind": "managed", "class": "orch_components:Worker", "args": {"source_sa": "motor"}},
                "reporter": {"class": "orch_components:Reporter", "args": {"expected": 3, "source_sa": "vision"}},
            }},
            "motor": {"components": {"producer": {"class": "orch_components:Producer", "args": {"count": 3}}}},
        },
        "servers": {"main": {"subarchitectures": ["vision"]}, "motion": {"subarchitectures": ["motor"]}},
    })
    run = embedded(cfg)
    main, motion = run.servers.servers
    assert main.endpoint != motion.endpoint
    assert main.system.host.subarchitectures == ["vision"] and motion.system.host.subarchitectures == ["motor"]
    who = Identity("test", "")
    wait_for(lambda: main.system.host.exists(who, "vision", "report"), what="the report on the main server")
    assert motion.system.host.entry_count("motor") == 3
    assert main.running.routes.remote == {"motor": motion.endpoint}
    assert run.stop().exit_code == 0


def test_a_second_ctrl_c_kills_what_is_still_stopping(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "impatient.yaml", {
        "orchestrator": {"stop_timeout": 600},
        "subarchitectures": {"work": {"components": {"stubborn": {"class": "orch_components:Stubborn"},
                                                     "fine": {"class": "orch_components:Recorder"}}}},
    })
    run = start_cast_run(tmp_path, cfg)
    components = run.cli_json("components")
    pids = [c["pid"] for c in components]
    fine_pid = next(c["pid"] for c in components if c["id"] == "fine")
    run.process.send_signal(signal.SIGINT)
    wait_for(lambda: "cast: stopping:" in run.output(), what="the orderly stop to begin")
    wait_for(lambda: "fine | stop() called" in run.output(), what="the first component to stop")
    # Its process ends a few milliseconds after stop() returns; only then is stubborn the one stopping.
    wait_for(lambda: gone(fine_pid), timeout=10, what="the first component to exit")
    run.process.send_signal(signal.SIGINT)
    assert run.process.wait(120) == 1  # far sooner than the 600 s stop timeout
    assert "stopping now: killing every component" in run.output()
    assert "stubborn exited with code -9 when stopped (killed)" in run.output()
    wait_for(lambda: all(gone(p) for p in pids), timeout=10, what="every process to be gone")


def test_a_second_ctrl_c_before_a_components_turn_to_stop_still_reports_it_killed(tmp_path: Path) -> None:
    # Stopped in reverse start order: "later" is stopping (its stop() hangs) when the second Ctrl-C
    # comes, "earlier" has not had its turn; both are killed, and both kills are the run's outcome.
    cfg = write_config(tmp_path / "impatient.yaml", {
        "orchestrator": {"stop_timeout": 600},
        "subarchitectures": {"work": {"components": {"earlier": {"class": "orch_components:Stubborn"},
                                                     "later": {"class": "orch_components:Stubborn"}}}},
    })
    run = start_cast_run(tmp_path, cfg)
    pids = [c["pid"] for c in run.cli_json("components")]
    run.process.send_signal(signal.SIGINT)
    wait_for(lambda: "cast: stopping:" in run.output(), what="the orderly stop to begin")
    run.process.send_signal(signal.SIGINT)
    assert run.process.wait(120) == 1  # far sooner than the 600 s stop timeout
    out = run.output()
    assert "earlier exited with code -9 when stopped (killed)" in out, out
    assert "later exited with code -9 when stopped (killed)" in out, out
    wait_for(lambda: all(gone(p) for p in pids), timeout=10, what="every process to be gone")


def test_a_component_that_cannot_start_is_not_restarted(tmp_path: Path, embedded: Callable[..., Embedded]) -> None:
    cfg = write_config(tmp_path / "missing.yaml", {
        "subarchitectures": {"work": {"components": {
            "ghost": {"class": "orch_components:Producer"},
        }}},
    })
    run = embedded(cfg)
    sup = run.orchestrator.supervisor
    assert sup is not None
    # The class imported when the file was checked, but this process will not find it.
    sup.components["ghost"].config.cls = "orch_components:Vanished"
    sup.components["ghost"].process.kill()  # type: ignore[union-attr]
    wait_for(lambda: sup.components["ghost"].phase is Phase.FAILED, what="the ghost to be given up")
    assert sup.components["ghost"].restarts == 1 and sup.components["ghost"].crashes == [-9, 2]
    assert "ghost could not start (exit code 2" in run.text()
    assert run.stop().exit_code == 1


def test_a_component_that_finishes_before_the_connect_check_is_reported_as_finished_not_missing(
    tmp_path: Path,
) -> None:
    # `fine` connects only after a pause, so the check happens once `quick` has surely exited. Both
    # end before the start barrier: `quick` never connects (a program that exits 0 at once), `broken`
    # fails in start(); a run() is held until every component started, so it cannot end earlier.
    late = f"import time, runpy, sys; time.sleep(3); sys.argv = ['cast.run', 'orch_components:Producer']; " \
           f"sys.path.insert(0, {str(COMPONENTS)!r}); runpy.run_module('cast.run', run_name='__main__')"
    cfg = write_config(tmp_path / "quick.yaml", {
        "subarchitectures": {"work": {"components": {
            "quick": {"language": "other", "run": [sys.executable, "-c", "pass"], "restart": "never"},
            "broken": {"class": "orch_components:FailingStart", "restart": "never"},
            "fine": {"language": "other", "run": [sys.executable, "-c", late]},
        }}},
        "orchestrator": {"connect_timeout": 30},
    })
    out = subprocess.run([CAST, "run", str(cfg), "--for", "1", "--no-status", "--runtime-dir", str(tmp_path / "rt")],
                         capture_output=True, text=True, timeout=120)
    assert "1 of 3 components running after" in out.stdout, out.stdout
    assert "finished already (exit code 0): quick; failed: broken" in out.stdout, out.stdout
    assert "not running" not in out.stdout


def test_the_final_summary_waits_for_a_stopped_components_session_to_end(tmp_path: Path) -> None:
    # The component's process exits but a detached child holds its connections for 1 s more: the
    # directory sees the heartbeat stream end only then, and the summary is taken after that.
    cfg = write_config(tmp_path / "lingering.yaml", {
        "subarchitectures": {"work": {"components": {"lingering": {"class": "orch_components:Lingering",
                                                                   "args": {"linger": 1.0}}}}},
    })
    summary = tmp_path / "summary.json"
    out = subprocess.run([CAST, "run", str(cfg), "--for", "0.5", "--no-status", "--runtime-dir", str(tmp_path / "rt"),
                          "--summary-json", str(summary)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    sessions = {c["id"]: c["session"] for c in json.loads(summary.read_text())["components"]}
    assert sessions == {"lingering": "disconnected"}, out.stdout
