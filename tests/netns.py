"""Network namespaces for the multi-host tests: hosts of their own, joined by veth pairs, and `cast agent` in them.

Each test makes its namespaces (the machine is root) and deletes them at the end. A test that
cannot make them fails with the reason; it never skips. Links (a veth pair, or a bridge in one
namespace with a veth pair to each of the others) are /24 subnets of
``10.<second>.x.0``; every namespace has its own routing table, so two tests may use the same ones.
"""

from __future__ import annotations

import os
import subprocess
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

import pytest

from tests.conftest import PYTHONPATH, SECRET, VENV_BIN, stop_process

CAST = str(VENV_BIN / "cast")


def ip(*args: str) -> None:
    """Run ``ip ARGS``; fail the test with its error if it fails."""
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.fail(f"`ip {' '.join(args)}` failed: {done.stderr.strip()} (network namespaces are required)")


def ns_pids(ns: str) -> set[int]:
    """The processes in namespace ``ns``."""
    done = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True)
    return {int(p) for p in done.stdout.split()}


class Namespaces:
    """Network namespaces made for one test (``with Namespaces() as net:``, or :meth:`close`), deleted at its end."""

    def __init__(self, second_octet: int = 214) -> None:
        self.tag = f"{os.getpid() % 100000}"
        self.second = second_octet
        self.net = 20 + os.getpid() % 200
        self.names: list[str] = []
        self.links = 0
        self.interfaces: dict[str, str] = {}  # namespace -> the veth end it got last (to cut its link)

    def __enter__(self) -> Namespaces:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Delete the namespaces (a process left in one keeps it alive until it ends)."""
        for ns in self.names:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.names.clear()

    def add(self, role: str) -> str:
        """A new namespace, ``cast<role><tag>``, with its loopback up."""
        ns = f"cast{role}{self.tag}"
        ip("netns", "add", ns)
        self.names.append(ns)
        ip("-n", ns, "link", "set", "lo", "up")
        return ns

    def link(self, a: str, b: str) -> tuple[str, str]:
        """Join namespaces ``a`` and ``b`` with a veth pair on a subnet of their own; their addresses on it."""
        i = self.links
        self.links += 1
        subnet = f"10.{self.second}.{(self.net + i) % 250}"
        if_a, if_b = f"v{self.tag}{i}a", f"v{self.tag}{i}b"
        ip("link", "add", if_a, "type", "veth", "peer", "name", if_b)
        addresses = []
        for ns, ifname, host in ((a, if_a, 1), (b, if_b, 2)):
            ip("link", "set", ifname, "netns", ns)
            ip("-n", ns, "addr", "add", f"{subnet}.{host}/24", "dev", ifname)
            ip("-n", ns, "link", "set", ifname, "up")
            addresses.append(f"{subnet}.{host}")
            self.interfaces[ns] = ifname
        return addresses[0], addresses[1]

    def bridge(self, hub: str, *spokes: str) -> list[str]:
        """Put ``hub`` and ``spokes`` on one subnet: a bridge in ``hub`` (its address ``.1``) and a veth pair from
        it to each spoke (``.2``, ``.3``, ...). Their addresses, the hub's first."""
        i = self.links
        self.links += 1
        subnet = f"10.{self.second}.{(self.net + i) % 250}"
        br = f"b{self.tag}{i}"
        ip("-n", hub, "link", "add", br, "type", "bridge")
        ip("-n", hub, "addr", "add", f"{subnet}.1/24", "dev", br)
        ip("-n", hub, "link", "set", br, "up")
        addresses = [f"{subnet}.1"]
        for k, ns in enumerate(spokes, 2):
            if_hub, if_ns = f"v{self.tag}{i}h{k}", f"v{self.tag}{i}s{k}"
            ip("link", "add", if_hub, "type", "veth", "peer", "name", if_ns)
            ip("link", "set", if_hub, "netns", hub)
            ip("link", "set", if_ns, "netns", ns)
            ip("-n", hub, "link", "set", if_hub, "master", br)
            ip("-n", hub, "link", "set", if_hub, "up")
            ip("-n", ns, "addr", "add", f"{subnet}.{k}/24", "dev", if_ns)
            ip("-n", ns, "link", "set", if_ns, "up")
            addresses.append(f"{subnet}.{k}")
        return addresses

    @staticmethod
    def exec(ns: str) -> list[str]:
        """The command prefix that runs a command in ``ns``."""
        return ["ip", "netns", "exec", ns]


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
        """The first line containing ``text``, waiting for it."""
        deadline = time.monotonic() + timeout
        while True:
            hit = next((x for x in self.lines if text in x), None)
            if hit is not None:
                return hit
            assert time.monotonic() < deadline, f"timed out waiting for {text!r}: " + "\n".join(self.lines[-30:])
            assert self.proc.poll() is None or any(text in x for x in self.lines), \
                f"exited ({self.proc.returncode}) before {text!r}: " + "\n".join(self.lines[-30:])
            time.sleep(0.05)


def start_agent(ns: str, listen: str, root: Path, secret_file: Path, env: dict[str, str],
                log_dir: Path | None = None, extra: Sequence[str] = ()) -> tuple[subprocess.Popen[str], str, Lines]:
    """`cast agent` in namespace ``ns`` on ``listen``: its process, the address it listens on, its output.

    ``ip netns exec`` execs the agent, so the process's pid is the agent's.
    """
    log = ["--log-dir", str(log_dir)] if log_dir is not None else []
    agent = subprocess.Popen(
        [*Namespaces.exec(ns), CAST, "agent", "--listen", listen, "--root", str(root), "--secret-file",
         str(secret_file), *log, *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=root)
    assert agent.stdout is not None
    first = agent.stdout.readline().strip()
    if not first.startswith("cast agent listening on "):
        agent.kill()
        pytest.fail(f"cast agent did not start in {ns}: {first}{agent.stdout.read()}")
    return agent, first.removeprefix("cast agent listening on ").split()[0], Lines(agent)


@dataclass
class TwoHosts:
    """Two namespaces joined by a veth pair: `cast run`'s (``orch``) and a `cast agent`'s (``agent``), one root.

    The root (a temporary directory holding the system secret) is the agent's ``--root`` and the
    working directory of every `cast` command run here, as the same checkout on both hosts would be.
    """

    net: Namespaces
    orch_ns: str
    agent_ns: str
    orch_ip: str
    agent_ip: str
    root: Path
    env: dict[str, str]  # the test's environment without CAST_*, with PYTHONPATH
    procs: list[subprocess.Popen[str]] = field(default_factory=list)
    agent: subprocess.Popen[str] | None = None
    agent_endpoint: str = ""
    agent_out: Lines | None = None

    @property
    def run_env(self) -> dict[str, str]:
        """The environment of `cast run` and `cast check`: the system secret the agent was given."""
        return dict(self.env, CAST_SECRET_FILE=str(self.root / "secret"))

    def start_agent(self, *extra: str) -> None:
        """`cast agent` in the agent's namespace, on its address, with the root's secret (and ``extra`` flags)."""
        self.agent, self.agent_endpoint, self.agent_out = start_agent(
            self.agent_ns, f"{self.agent_ip}:0", self.root, self.root / "secret", self.env, extra=extra)
        self.procs.append(self.agent)

    def cast(self, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        """``cast ARGS`` in the orchestrator's namespace, from the root; its result."""
        return subprocess.run([*Namespaces.exec(self.orch_ns), CAST, *args], capture_output=True, text=True,
                              env=self.run_env, cwd=self.root, timeout=timeout)

    def start_run(self, *args: str) -> tuple[subprocess.Popen[str], Lines]:
        """``cast run ARGS`` in the orchestrator's namespace, its output read on a thread."""
        run = subprocess.Popen([*Namespaces.exec(self.orch_ns), CAST, "run", *args], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, env=self.run_env, cwd=self.root)
        self.procs.append(run)
        return run, Lines(run)

    def wait_agent_alone(self, timeout: float = 10.0) -> None:
        """Until nothing but the agent is left in its namespace (no orphan); the agent still runs."""
        assert self.agent is not None and self.agent_out is not None
        deadline = time.monotonic() + timeout
        while left := ns_pids(self.agent_ns) - {self.agent.pid}:
            assert time.monotonic() < deadline, f"processes left in the agent's namespace: {left}"
            time.sleep(0.1)
        assert self.agent.poll() is None, "\n".join(self.agent_out.lines)


@contextmanager
def two_hosts(tmp_path: Path, second_octet: int) -> Iterator[TwoHosts]:
    """:class:`TwoHosts` on ``10.<second_octet>.x.0/24``, with the agent not started yet; all removed at the end."""
    net = Namespaces(second_octet=second_octet)
    hosts: TwoHosts | None = None
    try:
        orch_ns, agent_ns = net.add("orch"), net.add("agent")
        orch_ip, agent_ip = net.link(orch_ns, agent_ns)
        root = tmp_path / "root"
        root.mkdir()
        (root / "secret").write_text(SECRET + "\n")
        env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
        env["PYTHONPATH"] = PYTHONPATH
        hosts = TwoHosts(net, orch_ns, agent_ns, orch_ip, agent_ip, root, env)
        yield hosts
    finally:
        if hosts is not None:
            stop_all(hosts.procs)
        net.close()


def stop_all(procs: list[subprocess.Popen[str]]) -> None:
    """Terminate what is still running, the last started first (SIGKILL after 15 s)."""
    for proc in reversed(procs):
        stop_process(proc, 15)
