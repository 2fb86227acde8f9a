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
import time
from pathlib import Path

import yaml

from tests.conftest import PYTHONPATH, SECRET
from tests.netns import CAST, Lines, Namespaces, ns_pids, start_agent, stop_all
from tests.orchestrator.conftest import COMPONENTS

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


def test_cast_run_places_components_on_an_agents_host(tmp_path: Path) -> None:
    net = Namespaces()
    procs: list[subprocess.Popen[str]] = []
    try:
        orch_ns, agent_ns = net.add("orch"), net.add("agent")
        orch_ip, agent_ip = net.link(orch_ns, agent_ns)

        # The root: the same directory is the agent's --root and cast run's working directory.
        root = tmp_path / "root"
        (root / "comps").mkdir(parents=True)
        (root / "comps" / "loud_components.py").write_text(LOUD)
        (root / "secret").write_text(SECRET + "\n")
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        env["PYTHONPATH"] = PYTHONPATH

        agent, agent_ep, agent_out = start_agent(agent_ns, f"{agent_ip}:0", root, root / "secret", env)
        procs.append(agent)

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
        in_agent_ns = ns_pids(agent_ns)
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
        while (left := ns_pids(agent_ns) - {agent.pid}) - _agent_tree(agent.pid):
            assert time.monotonic() < deadline, f"processes left in the agent's namespace: {left}"
            time.sleep(0.1)
        assert agent.poll() is None, "\n".join(agent_out.lines)
        print(f"\nremote start: {attached}; {all_started}; cast run to all started {start_seconds:.2f} s; "
              f"stop {stop_seconds:.2f} s")
    finally:
        stop_all(procs)
        net.close()


def _agent_tree(pid: int) -> set[int]:
    """``ip netns exec`` execs the agent, so its pid is the agent's; nothing else may be left."""
    return {pid}
