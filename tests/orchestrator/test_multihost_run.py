"""`cast run` across hosts: components on another host started through its `cast agent`.

Two network namespaces joined by a veth pair on a private 10.214.x.0/24 made here: the
orchestrator (`cast run`, its servers in its process) in one, `cast agent` in the other. Two
components run on the agent's host, two locally; each watcher sees the writes of the writer
on the other host. The remote components' output reaches the orchestrator's log files,
`cast components --json` shows each component's host, and a clean stop leaves no process in the
agent's namespace but the agent. A test that cannot make namespaces fails with the reason.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import yaml

from tests.netns import ns_pids, two_hosts
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
    with two_hosts(tmp_path, second_octet=214) as hosts:
        # The root: the same directory is the agent's --root and cast run's working directory.
        root = hosts.root
        (root / "comps").mkdir(parents=True)
        (root / "comps" / "loud_components.py").write_text(LOUD)
        hosts.start_agent()
        assert hosts.agent is not None

        def comp(cls: str, host: str | None = None, **args: object) -> dict[str, object]:
            return {"class": f"loud_components:{cls}", **({"host": host} if host else {}),
                    **({"args": args} if args else {}), "privileged": True}

        (root / "system.yaml").write_text(yaml.safe_dump({
            "system": "mhrun",
            "python_path": [str(COMPONENTS), "comps"],
            "hosts": {"arm": hosts.agent_endpoint},
            "servers": {"main": {"listen": f"{hosts.orch_ip}:0", "subarchitectures": ["vision"]}},
            "orchestrator": {"lease_ms": 3000, "stop_timeout": 5, "connect_timeout": 60},
            "subarchitectures": {"vision": {"components": {
                "lwatch": comp("LoudWatcher"),
                "rwatch": comp("LoudWatcher", "arm"),
                "lwrite": comp("LoudWriter", sa="vision", count=COUNT),
                "rwrite": comp("LoudWriter", "arm", sa="vision", count=COUNT),
            }}},
        }, sort_keys=False))

        check = hosts.cast("check", "system.yaml", "--probe")
        assert check.returncode == 0, check.stdout + check.stderr
        assert "hosts: local (2 components), arm (2 components)" in check.stdout

        started = time.monotonic()
        run, out = hosts.start_run("system.yaml", "--no-status", "--runtime-dir", "rt", "--summary-json",
                                   "summary.json")
        attached = out.wait("attached to the agents of arm")
        all_started = out.wait("all 4 components started in")
        start_seconds = time.monotonic() - started

        def entries() -> dict[str, int]:
            done = hosts.cast("ls", "vision", "--json", "--runtime-dir", "rt")
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
                got = hosts.cast("get", "vision", f"seen-{w}-{r}", "--json", "--runtime-dir", "rt")
                assert str(COUNT) in got.stdout, (w, r, got.stdout, got.stderr)

        listed = hosts.cast("components", "--json", "--runtime-dir", "rt")
        assert listed.returncode == 0, listed.stderr
        placed = {c["id"]: c["host"] for c in json.loads(listed.stdout)}
        assert placed == {"lwatch": "local", "rwatch": "arm", "lwrite": "local", "rwrite": "arm"}, placed

        # Remote output: on the orchestrator's terminal and in its per-component log.
        for cid in ("rwatch", "rwrite"):
            out.wait(f"LOUD {cid} pid")
            assert f"LOUD {cid} pid" in (root / "rt" / "logs" / f"{cid}.log").read_text()
        remote_pids = {int(x.rsplit(" ", 1)[1]) for x in out.lines for cid in ("rwatch", "rwrite")
                       if f"LOUD {cid} pid" in x}
        in_agent_ns = ns_pids(hosts.agent_ns)
        assert remote_pids <= in_agent_ns, (remote_pids, in_agent_ns)

        stop_at = time.monotonic()
        run.send_signal(signal.SIGINT)
        code = run.wait(60)
        stop_seconds = time.monotonic() - stop_at
        assert code == 0, "\n".join(out.lines[-200:])  # a killed component's stacks are among them
        summary = json.loads((root / "summary.json").read_text())
        assert {c["id"]: c["host"] for c in summary["components"]} == placed
        assert summary["failures"] == []
        hosts.wait_agent_alone()  # ``ip netns exec`` execs the agent, so its pid is the agent's
        print(f"\nremote start: {attached}; {all_started}; cast run to all started {start_seconds:.2f} s; "
              f"stop {stop_seconds:.2f} s")
