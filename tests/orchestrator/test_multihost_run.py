"""`cast run` across hosts: components on another host started through its `cast agent` (issue 16, item 4).

Two network namespaces joined by a veth pair on a private 10.214.x.0/24 made here: the
orchestrator (`cast run`, its servers in its process) in one, `cast agent` in the other. Two
components run on the agent's host, two locally; each watcher sees the writes of the writer
on the other host. The remote components' output reaches the orchestrator's log files,
`cast components --json` shows each component's host, and a clean stop leaves no process in the
agent's namespace but the agent. A test that cannot make namespaces fails with the reason.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import PYTHONPATH, SECRET, VENV_BIN
from tests.orchestrator.conftest import COMPONENTS

CAST = str(VENV_BIN / "cast")
LOUD = '''\
import os

from barrier_components import BarrierWatcher, BarrierWriter


class LoudWriter(BarrierWriter):
    def start(self) -> None:
        print(f"LOUD {self.component_id} pid {os.getpid()}", flush=True)


class LoudWatcher(BarrierWatcher):
    def start(self) -> None:
        super().start()
        print(f"LOUD {self.component_id} pid {os.getpid()}", flush=True)
'''
COUNT = 25


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.fail(f"`ip {' '.join(args)}` failed: {done.stderr.strip()} (network namespaces are required)")


class Lines:
    """A process's output lines, read on a thread."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait(self, text: str, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while True:
            hit = next((x for x in self.lines if text in x), None)
            if hit is not None:
                return hit
            assert time.monotonic() < deadline, f"timed out waiting for {text!r}: " + "\n".join(self.lines[-30:])
            assert self.proc.poll() is None or any(text in x for x in self.lines), \
                f"exited ({self.proc.returncode}) before {text!r}: " + "\n".join(self.lines[-30:])
            time.sleep(0.05)


def _ns_pids(ns: str) -> set[int]:
    done = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True)
    return {int(p) for p in done.stdout.split()}


def test_cast_run_places_components_on_an_agents_host(tmp_path: Path) -> None:
    tag = f"{os.getpid() % 100000}"
    net = 20 + os.getpid() % 200
    orch_ns, agent_ns = f"castorch{tag}", f"castagent{tag}"
    orch_if, agent_if = f"vo{tag}", f"va{tag}"
    orch_ip, agent_ip = f"10.214.{net}.1", f"10.214.{net}.2"
    procs: list[subprocess.Popen[str]] = []
    try:
        _ip("netns", "add", orch_ns)
        _ip("netns", "add", agent_ns)
        _ip("link", "add", orch_if, "type", "veth", "peer", "name", agent_if)
        _ip("link", "set", orch_if, "netns", orch_ns)
        _ip("link", "set", agent_if, "netns", agent_ns)
        for ns, ifname, addr in ((orch_ns, orch_if, orch_ip), (agent_ns, agent_if, agent_ip)):
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", ifname)
            _ip("-n", ns, "link", "set", ifname, "up")
            _ip("-n", ns, "link", "set", "lo", "up")

        # The root: the same directory is the agent's --root and cast run's working directory.
        root = tmp_path / "root"
        (root / "comps").mkdir(parents=True)
        (root / "comps" / "loud_components.py").write_text(LOUD)
        (root / "secret").write_text(SECRET + "\n")
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        env["PYTHONPATH"] = PYTHONPATH

        agent = subprocess.Popen(
            ["ip", "netns", "exec", agent_ns, CAST, "agent", "--listen", f"{agent_ip}:0", "--root", str(root),
             "--secret-file", str(root / "secret")],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=root)
        procs.append(agent)
        assert agent.stdout is not None
        first = agent.stdout.readline().strip()
        assert first.startswith("cast agent listening on "), first
        agent_ep = first.removeprefix("cast agent listening on ").split()[0]
        agent_out = Lines(agent)

        def comp(cls: str, host: str | None = None, **args: object) -> dict[str, object]:
            return {"class": f"loud_components:{cls}", **({"host": host} if host else {}),
                    **({"args": args} if args else {}), "privileged": True}

        (root / "system.yaml").write_text(yaml.safe_dump({
            "system": "mhrun",
            "python_path": [str(COMPONENTS), "comps"],
            "hosts": {"arm": agent_ep},
            "servers": {"main": {"listen": f"{orch_ip}:0", "subarchitectures": ["vision"]}},
            "orchestrator": {"lease_ms": 3000, "stop_timeout": 5, "connect_timeout": 60},
            "subarchitectures": {"vision": {"components": {
                "lwatch": comp("LoudWatcher"),
                "rwatch": comp("LoudWatcher", "arm"),
                "lwrite": comp("LoudWriter", sa="vision", count=COUNT),
                "rwrite": comp("LoudWriter", "arm", sa="vision", count=COUNT),
            }}},
        }, sort_keys=False))

        run_env = dict(env, CAST_SECRET_FILE=str(root / "secret"))
        ns_exec = ["ip", "netns", "exec", orch_ns]
        check = subprocess.run([*ns_exec, CAST, "check", "system.yaml", "--probe"], capture_output=True, text=True,
                               env=run_env, cwd=root, timeout=60)
        assert check.returncode == 0, check.stdout + check.stderr
        assert "hosts: local (2 components), arm (2 components)" in check.stdout

        started = time.monotonic()
        run = subprocess.Popen([*ns_exec, CAST, "run", "system.yaml", "--no-status", "--runtime-dir", "rt",
                                "--summary-json", "summary.json"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=run_env, cwd=root)
        procs.append(run)
        out = Lines(run)
        attached = out.wait("attached to the agents of arm")
        all_started = out.wait("all 4 components started in")
        start_seconds = time.monotonic() - started

        def entries() -> dict[str, int]:
            done = subprocess.run([*ns_exec, CAST, "ls", "vision", "--json", "--runtime-dir", "rt"],
                                  capture_output=True, text=True, env=env, cwd=root, timeout=60)
            assert done.returncode == 0, done.stderr
            rows = json.loads(done.stdout)
            return {r["id"]: r for r in rows} if isinstance(rows, list) else rows

        deadline = time.monotonic() + 60
        wanted = {f"seen-{w}-{r}" for w in ("lwatch", "rwatch") for r in ("lwrite", "rwrite")}
        while not wanted <= set(entries()):
            assert time.monotonic() < deadline, f"watchers did not report: {sorted(entries())}\n" + "\n".join(
                out.lines[-30:])
            time.sleep(0.2)
        for w in ("lwatch", "rwatch"):
            for r in ("lwrite", "rwrite"):
                got = subprocess.run([*ns_exec, CAST, "get", "vision", f"seen-{w}-{r}", "--json", "--runtime-dir",
                                      "rt"], capture_output=True, text=True, env=env, cwd=root, timeout=60)
                assert str(COUNT) in got.stdout, (w, r, got.stdout, got.stderr)

        listed = subprocess.run([*ns_exec, CAST, "components", "--json", "--runtime-dir", "rt"], capture_output=True,
                                text=True, env=env, cwd=root, timeout=60)
        assert listed.returncode == 0, listed.stderr
        hosts = {c["id"]: c["host"] for c in json.loads(listed.stdout)}
        assert hosts == {"lwatch": "local", "rwatch": "arm", "lwrite": "local", "rwrite": "arm"}, hosts

        # Remote output: on the orchestrator's terminal and in its per-component log.
        for cid in ("rwatch", "rwrite"):
            out.wait(f"LOUD {cid} pid")
            assert f"LOUD {cid} pid" in (root / "rt" / "logs" / f"{cid}.log").read_text()
        remote_pids = {int(x.rsplit(" ", 1)[1]) for x in out.lines for cid in ("rwatch", "rwrite")
                       if f"LOUD {cid} pid" in x}
        in_agent_ns = _ns_pids(agent_ns)
        assert remote_pids <= in_agent_ns, (remote_pids, in_agent_ns)

        stop_at = time.monotonic()
        run.send_signal(signal.SIGINT)
        code = run.wait(60)
        stop_seconds = time.monotonic() - stop_at
        assert code == 0, "\n".join(out.lines[-40:])
        summary = json.loads((root / "summary.json").read_text())
        assert {c["id"]: c["host"] for c in summary["components"]} == hosts
        assert summary["failures"] == []
        deadline = time.monotonic() + 10
        while (left := _ns_pids(agent_ns) - {agent.pid}) - _agent_tree(agent.pid):
            assert time.monotonic() < deadline, f"processes left in the agent's namespace: {left}"
            time.sleep(0.1)
        assert agent.poll() is None, "\n".join(agent_out.lines)
        print(f"\nremote start: {attached}; {all_started}; cast run to all started {start_seconds:.2f} s; "
              f"stop {stop_seconds:.2f} s")
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        for ns in (orch_ns, agent_ns):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def _agent_tree(pid: int) -> set[int]:
    """``ip netns exec`` execs the agent, so its pid is the agent's; nothing else may be left."""
    return {pid}
