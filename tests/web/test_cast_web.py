"""`cast web` attached to a running system from another terminal, and bad input to it and to `cast run --web`."""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
from pathlib import Path

from tests.conftest import start_server, stop_process, wait_for
from tests.orchestrator.conftest import CAST
from tests.recording.conftest import cli_env
from tests.web.conftest import WebRun, http


def test_cast_web_attaches_to_the_running_system_and_stops_cleanly(web_run: WebRun) -> None:
    proc = subprocess.Popen([CAST, "web", "--listen", "127.0.0.1:0"], env=web_run.run.cli_environment(),
                            cwd=web_run.run.cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        first, second, third = (proc.stdout.readline() for _ in range(3))
        where = re.match(r"cast web: listening on (http://127\.0\.0\.1:(\d+)) \(loopback only: ", first)
        assert where is not None and where.group(2) != "0", first + second + third
        link = re.match(r"cast web: open (http://\S+/login\?key=\S+) \(this login link works once", second)
        assert link is not None and link.group(1).startswith(where.group(1)), second
        assert third.startswith("cast web: showing vision, motor of system 'webtest' from 127.0.0.1:"), third
        assert "read-only" in third
        assert http(where.group(1) + "/api/state")[0] == 401
        status, headers, _ = http(link.group(1))
        assert status == 303
        status, _, body = http(where.group(1) + "/api/state", {"Cookie": headers["set-cookie"].split(";")[0]})
        state = json.loads(body)
        assert status == 200 and [sa["name"] for sa in state["subarchitectures"]] == ["vision", "motor"]
        assert "planner" in {c["id"] for c in state["components"]}
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
        rest = proc.stdout.read()
        assert "cast web: stopped by SIGINT" in rest
        assert "the next one, for another browser" in rest  # the spent link was replaced
    finally:
        stop_process(proc, 5)


def cast(*args: str, cwd: Path | None = None, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([CAST, *args], capture_output=True, text=True, timeout=60, cwd=cwd, env=env)


def test_bad_addresses_are_refused_naming_them_and_nothing_starts(web_run: WebRun, tmp_path: Path) -> None:
    env = web_run.run.cli_environment()
    out = cast("web", "--listen", "127.0.0.1:x", env=env)
    assert out.returncode == 2
    assert "cast web: --listen '127.0.0.1:x': give HOST:PORT with a port from 0 to 65535" in out.stderr
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = cast("web", "--listen", f"127.0.0.1:{port}", env=env)
        assert out.returncode == 2
        assert f"cannot listen on 127.0.0.1:{port}: the address is in use" in out.stderr
        assert "--listen 127.0.0.1:0 picks one" in out.stderr
        # cast run binds the view before anything starts: a taken port ends it at once, nothing started.
        config = tmp_path / "system.yaml"
        config.write_text("system: nothing\nsubarchitectures:\n  a: {}\n")
        out = cast("run", str(config), "--no-status", "--runtime-dir", str(tmp_path / "rt"), "--for", "30",
                   f"--web=127.0.0.1:{port}", cwd=tmp_path, env=env)
        assert out.returncode == 2, out.stdout + out.stderr
        assert f"cannot listen on 127.0.0.1:{port}: the address is in use" in out.stderr
        assert "--web 127.0.0.1:0 picks one" in out.stderr
        assert "started" not in out.stdout
    out = cast("run", str(config), "--web=nowhere", "--runtime-dir", str(tmp_path / "rt"), cwd=tmp_path, env=env)
    assert out.returncode == 2 and "--web 'nowhere': give HOST:PORT" in out.stderr
    out = cast("web", "--listen", "192.0.2.1:0", env=env)  # TEST-NET: not an address of this machine
    assert out.returncode == 2 and "cannot listen on 192.0.2.1:0" in out.stderr
    assert "give an address of this machine" in out.stderr


def test_cast_web_with_no_system_says_so(tmp_path: Path) -> None:
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]  # nobody listens there
    env = {"PATH": "/usr/bin:/bin", "CAST_SECRET": "x" * 40, "CAST_RUNTIME_DIR": str(tmp_path)}
    out = cast("web", "--endpoint", f"127.0.0.1:{port}", "--listen", "127.0.0.1:0", env=env)
    assert out.returncode == 2
    assert f"cast web: no system answers at 127.0.0.1:{port}" in out.stderr


def test_the_page_says_when_the_system_stops_answering(tmp_path: Path) -> None:
    server = start_server(tmp_path, {"system": "brief", "subarchitectures": {"a": {}}})
    env = {**cli_env(), "CAST_RUNTIME_DIR": str(tmp_path / "none")}
    proc = subprocess.Popen([CAST, "web", "--endpoint", server.endpoint, "--listen", "127.0.0.1:0"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(3)]
        link = re.search(r"open (http://\S+/login\?key=\S+) ", lines[1])
        assert link is not None, lines
        base = link.group(1).split("/login")[0]
        cookie = http(link.group(1))[1]["set-cookie"].split(";")[0]
        assert json.loads(http(base + "/api/state", {"Cookie": cookie})[2])["error"] == ""
        server.stop()
        state = wait_for(lambda: (s := json.loads(http(base + "/api/state", {"Cookie": cookie})[2]))["error"] and s,
                         30, "the page to say the system does not answer")
        assert state["error"] == f"no answer from {server.endpoint} (has the system stopped?)"
        assert state["connected"] is False and state["system"] == "brief"  # the last state is kept
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
        out = proc.stdout.read()
        assert f"cast web: cannot read the system: no answer from {server.endpoint}" in out
        assert "reconnecting" not in out  # the client library's warnings are not repeated every few seconds
    finally:
        stop_process(proc, 5)
        server.stop()
