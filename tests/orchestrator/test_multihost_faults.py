"""Faults across hosts (docs/multihost.md): `cast run` in one network namespace, `cast agent` in another.

One pair of namespaces joined by a veth pair on a private 10.215.x.0/24 serves the whole module;
each test starts its own agent (some kill it) on a fixed port, and its own `cast run`. A remote
ticker prints numbered lines (each after a successful write to the orchestrator's server), so
the orchestrator's log shows whether output was lost or came twice; a local ticker and a local
watcher show that the rest of the system keeps running. Tests never assert wall-clock times:
each waits within a generous guard and prints what it measured (docs/multihost.md's fault
table). A test that cannot make namespaces fails with the reason.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import psutil
import pytest
import yaml

from tests.conftest import PYTHONPATH, SECRET, VENV_BIN
from tests.netns import Namespaces, ip, ns_pids, stop_all

CAST = str(VENV_BIN / "cast")
GUARD_S = 60.0
AGENT_PORT = 7070
FAULTS = '''\
import os

from google.protobuf.wrappers_pb2 import Int64Value

import cast
from cast import Operation


class Ticker(cast.UnmanagedComponent):
    """Overwrites tick-<id> every 0.1 s; prints TICK <id> <n> after each write that worked."""

    def start(self) -> None:
        print(f"PID {self.component_id} {os.getpid()}", flush=True)
        if not self.exists(f"tick-{self.component_id}"):  # a restart finds it
            self.add(f"tick-{self.component_id}", Int64Value(value=0))

    def run(self) -> None:
        n = 0
        while not self.wait_for_stop(0.1):
            try:
                self.overwrite(f"tick-{self.component_id}", Int64Value(value=n + 1))
            except cast.CastError as exc:
                print(f"RETRY {self.component_id} {exc.code}", flush=True)
                continue
            n += 1
            print(f"TICK {self.component_id} {n}", flush=True)


class Seer(cast.UnmanagedComponent):
    """Prints SAW <id> <entry> <version> for each overwrite (of a tick entry)."""

    def start(self) -> None:
        self.on_change([cast.operation_filter(Operation.OVERWRITE)], self._changed)

    def _changed(self, change: cast.WorkingMemoryChange) -> None:
        print(f"SAW {self.component_id} {change.id} {change.version}", flush=True)
'''


class Lines:
    """A process's output lines, read on a thread, each with the time it arrived."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self.times: list[float] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.times.append(time.monotonic())
            self.lines.append(line.rstrip("\n"))

    def tail(self) -> str:
        return "\n".join(self.lines[-40:])

    def wait(self, pattern: str, after: int = 0, timeout: float = GUARD_S) -> int:
        """The index of the first line from ``after`` on that matches ``pattern`` (a regular expression)."""
        deadline = time.monotonic() + timeout
        rx = re.compile(pattern)
        exited: float | None = None
        while True:
            for index in range(after, len(self.lines)):
                if rx.search(self.lines[index]):
                    return index
            assert time.monotonic() < deadline, f"timed out waiting for {pattern!r}:\n{self.tail()}"
            if self.proc.poll() is not None:
                if exited is None:
                    exited = time.monotonic()  # the reader thread may still be taking its last lines
                assert time.monotonic() - exited < 1.0, \
                    f"exited ({self.proc.returncode}) before {pattern!r}:\n{self.tail()}"
            time.sleep(0.02)

    def matching(self, pattern: str, after: int = 0) -> list[str]:
        rx = re.compile(pattern)
        return [x for x in self.lines[after:] if rx.search(x)]


@dataclass
class Net:
    """The orchestrator's namespace and the agent's, joined by a veth pair whose agent end can be cut."""

    orch_ns: str
    agent_ns: str
    agent_if: str
    orch_ip: str
    agent_ip: str
    exec = staticmethod(Namespaces.exec)
    pids = staticmethod(ns_pids)

    def cut(self) -> None:
        ip("-n", self.agent_ns, "link", "set", self.agent_if, "down")

    def restore(self) -> None:
        ip("-n", self.agent_ns, "link", "set", self.agent_if, "up")


@pytest.fixture(scope="module")
def net() -> Iterator[Net]:
    with Namespaces(second_octet=215) as spaces:
        orch, agent = spaces.add("fo"), spaces.add("fa")
        orch_ip, agent_ip = spaces.link(orch, agent)
        yield Net(orch, agent, spaces.interfaces[agent], orch_ip, agent_ip)


def gone(pid: int) -> bool:
    """Whether ``pid`` is dead (reaped, or a zombie)."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def wait_gone(pids: set[int], what: str) -> float:
    """Seconds until every pid in ``pids`` is dead; fails after the guard."""
    started = time.monotonic()
    while not all(gone(p) for p in pids):
        assert time.monotonic() - started < GUARD_S, f"{what}: {[p for p in pids if not gone(p)]} still run"
        time.sleep(0.01)
    return time.monotonic() - started


class System:
    """An agent in the agent's namespace and a `cast run` in the orchestrator's, over one root directory."""

    def __init__(self, net: Net, root: Path, name: str, components: dict[str, dict[str, object]],
                 lease_ms: int) -> None:
        self.net = net
        self.root = root
        (root / "comps").mkdir(parents=True)
        (root / "comps" / "fault_components.py").write_text(FAULTS)
        (root / "secret").write_text(SECRET + "\n")
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        self.env["PYTHONPATH"] = PYTHONPATH
        self.procs: list[subprocess.Popen[str]] = []
        self.agent: subprocess.Popen[str] | None = None
        self.agent_out: Lines | None = None
        (root / "system.yaml").write_text(yaml.safe_dump({
            "system": name,
            "python_path": ["comps"],
            "hosts": {"arm": f"{net.agent_ip}:{AGENT_PORT}"},
            "servers": {"main": {"listen": f"{net.orch_ip}:0", "subarchitectures": ["vision"]}},
            "orchestrator": {"lease_ms": lease_ms, "stop_timeout": 3, "connect_timeout": 60},
            "subarchitectures": {"vision": {"components": components}},
        }, sort_keys=False))
        self.run: subprocess.Popen[str] | None = None
        self.out: Lines | None = None

    def start_agent(self) -> None:
        agent = subprocess.Popen(
            [*self.net.exec(self.net.agent_ns), CAST, "agent", "--listen", f"{self.net.agent_ip}:{AGENT_PORT}",
             "--root", str(self.root), "--secret-file", str(self.root / "secret")],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=self.env, cwd=self.root)
        self.procs.append(agent)
        assert agent.stdout is not None
        first = agent.stdout.readline().strip()
        assert first.startswith("cast agent listening on "), first
        self.agent, self.agent_out = agent, Lines(agent)

    def start_run(self) -> Lines:
        run = subprocess.Popen(
            [*self.net.exec(self.net.orch_ns), CAST, "run", "system.yaml", "--no-status", "--runtime-dir", "rt",
             "--summary-json", "summary.json"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env=dict(self.env, CAST_SECRET_FILE=str(self.root / "secret")), cwd=self.root)
        self.procs.append(run)
        self.run, self.out = run, Lines(run)
        self.out.wait(r"all \d+ components started in")
        return self.out

    def pid_of(self, cid: str, after: int = 0) -> int:
        assert self.out is not None
        index = self.out.wait(rf"PID {cid} \d+", after)
        return int(self.out.lines[index].rsplit(" ", 1)[1])

    def stop_run(self) -> tuple[int, dict[str, object]]:
        assert self.run is not None and self.out is not None
        self.run.send_signal(signal.SIGINT)
        code = self.run.wait(GUARD_S)
        time.sleep(0.2)  # the reader thread takes the last lines
        return code, json.loads((self.root / "summary.json").read_text())

    def log(self, cid: str) -> str:
        return (self.root / "rt" / "logs" / f"{cid}.log").read_text()

    def close(self) -> None:
        self.net.restore()
        stop_all(self.procs)


@pytest.fixture
def system(net: Net, tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[object]:
    made: list[System] = []

    def make(components: dict[str, dict[str, object]], lease_ms: int = 3000) -> System:
        made.append(System(net, tmp_path / "root", f"faults{len(made)}{request.node.name[-6:]}", components,
                           lease_ms))
        return made[-1]

    yield make
    for s in made:
        s.close()


def comp(cls: str, host: str | None = None, restart: str | None = None) -> dict[str, object]:
    return {"class": f"fault_components:{cls}", **({"host": host} if host else {}),
            **({"restart": {"policy": restart, "backoff": 0.2}} if restart else {}), "privileged": True}


def ticks(lines: list[str], cid: str) -> list[int]:
    return [int(x.rsplit(" ", 1)[1]) for x in lines if re.search(rf"TICK {cid} \d+$", x)]


def test_a_sigkilled_orchestrator_leaves_no_process_on_the_agents_host(net: Net, system) -> None:  # type: ignore[no-untyped-def]
    s: System = system({"lticker": comp("Ticker"), "rticker": comp("Ticker", "arm")}, lease_ms=3000)
    s.start_agent()
    out = s.start_run()
    remote, local = s.pid_of("rticker"), s.pid_of("lticker")
    assert remote in net.pids(net.agent_ns)
    out.wait("TICK rticker 3")
    assert s.run is not None and s.agent is not None
    killed = time.monotonic()
    s.run.kill()  # `ip netns exec` execs cast run: this is its pid
    s.run.wait()
    local_s = wait_gone({local}, "the local component of a SIGKILLed orchestrator")
    wait_gone({remote}, "the remote component of a SIGKILLed orchestrator")
    remote_s = time.monotonic() - killed
    assert net.pids(net.agent_ns) == {s.agent.pid}, "processes left in the agent's namespace"
    assert s.agent.poll() is None
    assert s.agent_out is not None
    deadline = time.monotonic() + 5
    while not any("lease expired" in x for x in s.agent_out.lines) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert any("lease expired" in x for x in s.agent_out.lines), s.agent_out.lines
    print(f"\norchestrator SIGKILLed: the agent stopped the remote component {remote_s:.2f} s later (lease 3.0 s, "
          f"grace 3 s); the local one died {local_s:.2f} s later (PR_SET_PDEATHSIG)")


def test_a_sigkilled_agents_components_fail_and_the_rest_keeps_running(net: Net, system) -> None:  # type: ignore[no-untyped-def]
    s: System = system({"lticker": comp("Ticker"), "lseer": comp("Seer"),
                        "rticker": comp("Ticker", "arm", restart="on-failure")}, lease_ms=3000)
    s.start_agent()
    out = s.start_run()
    remote = s.pid_of("rticker")
    out.wait("TICK rticker 3")
    assert s.agent is not None
    killed = time.monotonic()
    s.agent.kill()
    s.agent.wait()
    died = wait_gone({remote}, "the remote component of a SIGKILLed agent")
    lost = out.wait(r"host arm: lost: .*its components failed: rticker")
    detected = out.times[lost] - killed
    # The rest keeps running: the local ticker writes and the local watcher sees it, after the loss.
    seen = out.wait(r"SAW lseer tick-lticker \d+", lost + 1)
    out.wait(r"SAW lseer tick-lticker \d+", seen + 1)
    time.sleep(2.0)  # no restart loop against a dead agent
    assert not out.matching(r"rticker.*restarting|cannot launch", lost), out.tail()
    assert not out.matching(r"PID rticker", lost)
    code, summary = s.stop_run()
    assert code == 1, out.tail()
    failures = summary["failures"]
    assert isinstance(failures, list)
    assert any("rticker: host 'arm' lost (1 time(s)); not running at the end" in f for f in failures), failures
    assert not any(f.startswith(("lticker", "lseer")) for f in failures), failures
    print(f"\nagent SIGKILLed: its component died {died:.2f} s later (PR_SET_PDEATHSIG); the orchestrator "
          f"reported the host lost {detected:.2f} s after the kill (lease 3.0 s): {out.lines[lost]}")


def test_an_agent_restarted_while_the_system_runs_rejoins(net: Net, system) -> None:  # type: ignore[no-untyped-def]
    s: System = system({"lticker": comp("Ticker"), "rticker": comp("Ticker", "arm", restart="on-failure"),
                        "rnever": comp("Ticker", "arm", restart="never")}, lease_ms=3000)
    s.start_agent()
    out = s.start_run()
    first = s.pid_of("rticker")
    out.wait("TICK rticker 3")
    assert s.agent is not None
    s.agent.kill()
    s.agent.wait()
    wait_gone({first}, "the remote component of a SIGKILLed agent")
    restarted = time.monotonic()
    s.start_agent()  # the same port: the orchestrator keeps trying to attach
    back = out.wait(r"host arm: back: attached to the agent")
    rejoined = out.times[back] - restarted
    lost = out.wait(r"host arm: lost: .*its components failed: rnever, rticker")
    assert lost < back
    again = out.wait(r"PID rticker \d+", back)
    second = int(out.lines[again].rsplit(" ", 1)[1])
    assert second != first
    out.wait(r"TICK rticker \d+", again)
    assert out.matching(r"rnever: host 'arm' lost; not restarted", lost), out.tail()
    assert not out.matching(r"PID rnever", lost)
    code, summary = s.stop_run()
    assert code == 1, out.tail()
    rows = {c["id"]: c for c in summary["components"]}  # type: ignore[attr-defined]
    assert rows["rticker"]["restarts"] == 1, rows["rticker"]
    failures = summary["failures"]
    assert isinstance(failures, list)
    assert any("rticker: host 'arm' lost (1 time(s)); restarted" in f for f in failures), failures
    assert any("rnever: host 'arm' lost (1 time(s)); not running at the end" in f for f in failures), failures
    print(f"\nagent SIGKILLed and restarted: the orchestrator attached again {rejoined:.2f} s after the restart "
          f"({out.lines[lost]}); rticker restarted once (pid {first} -> {second}), rnever (restart: never) not")


def test_a_link_cut_within_the_lease_restarts_nothing_and_loses_no_line(net: Net, system) -> None:  # type: ignore[no-untyped-def]
    s: System = system({"lticker": comp("Ticker"), "rticker": comp("Ticker", "arm", restart="on-failure")},
                       lease_ms=4000)
    s.start_agent()
    out = s.start_run()
    pid = s.pid_of("rticker")
    out.wait("TICK rticker 5")
    cut_at = len(out.lines)
    before = max(ticks(out.lines, "rticker"))
    net.cut()
    cut = time.monotonic()
    time.sleep(1.5)
    net.restore()
    cut_s = time.monotonic() - cut
    resumed = out.wait(rf"TICK rticker {before + 20}$", cut_at)
    caught_up = out.times[resumed] - (cut + cut_s)
    assert not out.matching(r"host arm: lost|restarting|PID rticker", cut_at), out.tail()
    assert pid in net.pids(net.agent_ns)
    code, summary = s.stop_run()
    assert code == 0, out.tail()
    assert summary["failures"] == []
    logged = ticks(s.log("rticker").splitlines(), "rticker")
    assert logged == list(range(1, len(logged) + 1)), "lines lost or duplicated in the orchestrator's log"
    retries = len(out.matching(r"RETRY rticker", cut_at))
    print(f"\nlink cut for {cut_s:.2f} s (lease 4.0 s): nothing restarted, {len(logged)} numbered lines in the "
          f"orchestrator's log with no gap or duplicate, {retries} failed writes retried, the remote ticker "
          f"20 ticks on {caught_up:.2f} s after the link returned")


def test_a_link_cut_longer_than_the_lease_loses_the_host_until_it_returns(net: Net, system) -> None:  # type: ignore[no-untyped-def]
    s: System = system({"lticker": comp("Ticker"), "rticker": comp("Ticker", "arm", restart="on-failure")},
                       lease_ms=2000)
    s.start_agent()
    out = s.start_run()
    first = s.pid_of("rticker")
    out.wait("TICK rticker 3")
    cut_at = len(out.lines)
    net.cut()
    cut = time.monotonic()
    lost = out.wait(r"host arm: lost: no answer from its agent .*its components failed: rticker", cut_at)
    detected = out.times[lost] - cut
    wait_gone({first}, "the component of a session whose lease ran out")
    stopped = time.monotonic() - cut
    assert not out.matching(r"PID rticker|restarting in", cut_at), out.tail()
    net.restore()
    restored = time.monotonic()
    back = out.wait(r"host arm: back: attached to the agent", lost)
    rejoined = out.times[back] - restored
    again = out.wait(r"PID rticker \d+", back)
    out.wait(r"TICK rticker \d+", again)
    second = int(out.lines[again].rsplit(" ", 1)[1])
    assert second != first
    code, summary = s.stop_run()
    assert code == 1, out.tail()
    rows = {c["id"]: c for c in summary["components"]}  # type: ignore[attr-defined]
    assert rows["rticker"]["restarts"] == 1, rows["rticker"]
    assert not any(str(f).startswith("lticker") for f in summary["failures"]), summary["failures"]  # type: ignore[attr-defined]
    print(f"\nlink cut longer than the lease (2.0 s): host lost {detected:.2f} s after the cut, the agent stopped "
          f"the component {stopped:.2f} s after it; link restored {restored - cut:.2f} s after the cut, attached "
          f"again {rejoined:.2f} s later, rticker restarted once (pid {first} -> {second})")
