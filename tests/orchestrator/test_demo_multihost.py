"""The multi-host demo: `cast run configs/demo-multihost.yaml --for N` across three hosts.

Three network namespaces made here: the orchestrator's (`cast run`, its servers and the Python
components), the robot's (`cast agent` on port 7071, the C++ segmenter) and the workstation's
(`cast agent` on port 7072, the Java colour recogniser), on one subnet (a bridge in the
orchestrator's namespace, a veth pair to each of the others). The file's variables point at
their addresses. The demo answers all its questions, the remote components' lines reach the
orchestrator's output and logs, `cast components --json` and the summary show each component on
its host, and a clean exit 0 leaves no process in the agents' namespaces but the agents. A test
that cannot make namespaces fails with the reason.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import time
from pathlib import Path

from tests.conftest import ROOT, SECRET
from tests.netns import CAST, Lines, Namespaces, ns_pids, start_agent, stop_all
from tests.orchestrator.test_demo import demo_builds

CONFIG = "configs/demo-multihost.yaml"
SECONDS = 18  # the coordinator asks its last question 14.5 s after run() is released
HOSTS = {"segmenter": "robot", "colour": "workstation", "shape": "local", "answerer": "local", "coordinator": "local"}


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def test_the_multihost_demo_answers_every_question_across_three_hosts(demo_built: Path, tmp_path: Path) -> None:
    demo_builds()
    net = Namespaces(second_octet=215)
    procs: list[subprocess.Popen[str]] = []
    try:
        orch_ns, robot_ns, ws_ns = net.add("orch"), net.add("robot"), net.add("ws")
        servers_ip, robot_ip, ws_ip = net.bridge(orch_ns, robot_ns, ws_ns)

        # Every host: the same checkout (the agents' --root, cast run's working directory) and the secret.
        secret = tmp_path / "secret"
        secret.write_text(SECRET + "\n")
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        agents = {}
        for name, ns, listen in (("robot", robot_ns, f"{robot_ip}:7071"), ("workstation", ws_ns, f"{ws_ip}:7072")):
            agent, _, lines = start_agent(ns, listen, ROOT, secret, env, tmp_path / f"{name}-logs")
            procs.append(agent)
            agents[name] = (ns, agent, lines)

        sets = ["--set", f"ROBOT_ADDRESS={robot_ip}", "--set", f"WORKSTATION_ADDRESS={ws_ip}",
                "--set", f"SERVERS_ADDRESS={servers_ip}"]
        run_env = dict(env, CAST_SECRET_FILE=str(secret))
        ns_exec = Namespaces.exec(orch_ns)
        check = subprocess.run([*ns_exec, CAST, "check", CONFIG, "--probe", *sets], capture_output=True, text=True,
                               env=run_env, cwd=ROOT, timeout=60)
        assert check.returncode == 0, check.stdout + check.stderr
        assert "hosts: local (3 components), robot (1 component), workstation (1 component)" in check.stdout

        started = time.monotonic()
        runtime, summary = tmp_path / "rt", tmp_path / "summary.json"
        run = subprocess.Popen([*ns_exec, CAST, "run", CONFIG, "--for", str(SECONDS), "--no-status", "--runtime-dir",
                                str(runtime), "--summary-json", str(summary), *sets],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=run_env, cwd=ROOT)
        procs.append(run)
        out = Lines(run)
        out.wait("attached to the agents of robot")
        out.wait("cast: all 5 components started in")

        # Each remote component runs in its host's namespace; cast components shows each on its host.
        for name, marker in (("robot", "build/cpp/bin/segmenter"), ("workstation", "cast.examples.ColourRecogniser")):
            ns, agent, _ = agents[name]
            assert any(marker in cmdline(p) for p in ns_pids(ns) - {agent.pid}), (name, ns_pids(ns))
        listed = subprocess.run([*ns_exec, CAST, "components", "--json", "--runtime-dir", str(runtime)],
                                capture_output=True, text=True, env=env, cwd=ROOT, timeout=60)
        assert listed.returncode == 0, listed.stderr
        assert {c["id"]: c["host"] for c in json.loads(listed.stdout)} == HOSTS

        code = run.wait(SECONDS + 60)
        seconds = time.monotonic() - started
        out.wait("every component ran and stopped cleanly", timeout=10)  # all output read
        text = "\n".join(out.lines)
        assert code == 0, text

        # Every question answered; the remote components' lines in the orchestrator's output and logs.
        assert "coordinator | 8 of 8 questions answered" in text, text
        assert len(re.findall(r"^coordinator \| q\d .* -> ", text, re.M)) == 8, text
        assert "segmenter | frame 1: new region obj-1" in text
        assert re.search(r"^\s*colour \| obj-\d is \w+ \(task-\d+, \d\.\d s\)$", text, re.M), text
        assert "frame 1: new region obj-1" in (runtime / "logs" / "segmenter.log").read_text()
        assert " is " in (runtime / "logs" / "colour.log").read_text()
        assert "hosts: robot: segmenter; workstation: colour; local: shape, answerer, coordinator" in text

        data = json.loads(summary.read_text())
        assert data["failures"] == [] and data["system"] == "scene-description"
        assert {c["id"]: c["host"] for c in data["components"]} == HOSTS
        assert {c["id"]: c["language"] for c in data["components"]} == {
            **dict.fromkeys(HOSTS, "python"), "segmenter": "cpp", "colour": "java"}

        # A clean stop leaves nothing in the agents' namespaces but the agents, still running.
        deadline = time.monotonic() + 10
        for name, (ns, agent, lines) in agents.items():
            while left := ns_pids(ns) - {agent.pid}:
                assert time.monotonic() < deadline, f"processes left on {name}: {[cmdline(p) for p in left]}"
                time.sleep(0.1)
            assert agent.poll() is None, "\n".join(lines.lines)
        print(f"\nmulti-host demo: cast run --for {SECONDS} took {seconds:.1f} s")
    finally:
        stop_all(procs)
        net.close()
