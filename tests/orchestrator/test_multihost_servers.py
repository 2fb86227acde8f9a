"""A server on another host: `cast run` starts it through that host's `cast agent`.

Two network namespaces joined by a veth pair on a private 10.217.x.0/24 made here: `cast run` (the
directory server `main`, SA `near`, in its process) in one; `cast agent` in the other, which starts
the server `far` (SA `far`, `host: arm`) as `cast serve --server far` with the agent's secret. On
each side a writer adds to the other side's SA and a watcher watches its own: every change is
seen (the start barrier holds both servers' components). A clean stop leaves nothing in the
agent's namespace but the agent. A test that cannot make namespaces fails with the reason.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import yaml

from tests.netns import two_hosts
from tests.orchestrator.conftest import COMPONENTS

COUNT = 25


def test_cast_run_starts_a_server_on_an_agents_host(tmp_path: Path) -> None:
    with two_hosts(tmp_path, second_octet=217) as hosts:
        hosts.start_agent()
        orch_ip, agent_ip, root = hosts.orch_ip, hosts.agent_ip, hosts.root

        def comp(cls: str, host: str | None = None, **args: object) -> dict[str, object]:
            return {"class": f"barrier_components:{cls}", **({"host": host} if host else {}),
                    **({"args": args} if args else {}), "privileged": True}

        (root / "system.yaml").write_text(yaml.safe_dump({
            "system": "mhservers",
            "python_path": [str(COMPONENTS)],
            "hosts": {"arm": hosts.agent_endpoint},
            "servers": {
                "main": {"listen": f"{orch_ip}:0", "subarchitectures": ["near"]},
                "far": {"listen": f"{agent_ip}:0", "host": "arm", "subarchitectures": ["far"]},
            },
            "orchestrator": {"lease_ms": 3000, "stop_timeout": 5, "connect_timeout": 60},
            "subarchitectures": {
                "near": {"components": {
                    "lwatch": comp("BarrierWatcher"),
                    "lwrite": comp("BarrierWriter", sa="far", count=COUNT),
                }},
                "far": {"components": {
                    "rwatch": comp("BarrierWatcher", "arm"),
                    "rwrite": comp("BarrierWriter", "arm", sa="near", count=COUNT),
                }},
            },
        }, sort_keys=False))

        check = hosts.cast("check", "system.yaml", "--probe")
        assert check.returncode == 0, check.stdout + check.stderr

        started = time.monotonic()
        run, out = hosts.start_run("system.yaml", "--no-status", "--runtime-dir", "rt", "--summary-json",
                                   "summary.json")
        far_line = out.wait("server far on host arm: listening on")
        assert f"reached at {agent_ip}:" in far_line, far_line
        all_started = out.wait("all 4 components started in")
        start_seconds = time.monotonic() - started

        def get(sa: str, entry: str) -> str:
            got = hosts.cast("get", sa, entry, "--json", "--runtime-dir", "rt")
            return got.stdout if got.returncode == 0 else ""

        # Each watcher saw every change the writer of the other host made to its SA.
        deadline = time.monotonic() + 60
        for sa, entry in (("far", "seen-rwatch-lwrite"), ("near", "seen-lwatch-rwrite")):
            while str(COUNT) not in (text := get(sa, entry)):
                assert time.monotonic() < deadline, f"{sa}/{entry}: {text!r}\n" + "\n".join(out.lines[-30:])
                time.sleep(0.2)

        # The far server runs in the agent's namespace; its output comes back to the orchestrator's log.
        server_log = root / "rt" / "logs" / "server-far.log"
        assert "listening on" in server_log.read_text()
        assert "start barrier released" in server_log.read_text()

        stop_at = time.monotonic()
        run.send_signal(signal.SIGINT)
        code = run.wait(60)
        stop_seconds = time.monotonic() - stop_at
        assert code == 0, "\n".join(out.lines[-200:])  # a killed component's stacks are among them
        summary = json.loads((root / "summary.json").read_text())
        assert summary["failures"] == []
        # The far server's SA is in the summary too, asked over the network (lwrite's entries, rwatch's report).
        sas = {row["name"]: row for row in summary["subarchitectures"]}
        assert set(sas) == {"near", "far"}, sas
        assert sas["far"]["entries"] >= COUNT + 2 and sas["far"]["endpoint"].startswith(f"{agent_ip}:"), sas["far"]
        assert sas["far"]["types"].get("google.protobuf.Int64Value", 0) >= COUNT + 2, sas["far"]
        # The metrics of both servers: the far one counted the writes into far, and was asked over the network.
        metrics = summary["metrics"]
        assert metrics["servers"] == 2, metrics
        writes = {(cell["from_sa"], cell["to_sa"]): cell["writes"] for cell in metrics["traffic"]}
        assert writes[("near", "far")] == COUNT + 1 and writes[("far", "near")] == COUNT + 1, writes
        hosts.wait_agent_alone()
        print(f"\n{far_line}; {all_started}; cast run to all started {start_seconds:.2f} s; stop {stop_seconds:.2f} s")
