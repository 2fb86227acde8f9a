"""Multi-host: server and components in separate network namespaces with their own addresses.

Two namespaces joined by a veth pair on a private 10.213.x.0/24 made here, used
only inside them. The server runs in one, the components (a writer, a watcher,
a managed component holding a lock and a task) in the other. The link is cut
for a few seconds and restored: nothing acknowledged is lost, the watcher
catches up with no gap, and the lock and task of the component whose session
lapsed are released. If namespaces are not permitted the test fails (it does not skip).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from cast.auth import TokenSigner
from cast.core.records import Identity
from tests.conftest import PYTHONPATH, SECRET, VENV_BIN
from tests.reliability.figures import record

COMPONENTS = Path(__file__).resolve().parent / "components"


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

    def wait(self, predicate: object, timeout: float = 60.0, what: str = "") -> None:
        deadline = time.monotonic() + timeout
        while not predicate(self.lines):  # type: ignore[operator]
            assert time.monotonic() < deadline, f"timed out waiting for {what}: {self.lines[-5:]}"
            time.sleep(0.05)


def test_link_cut_between_namespaces_loses_nothing_and_releases_the_lost_session(tmp_path: Path) -> None:
    tag = f"{os.getpid() % 100000}"
    net = 20 + os.getpid() % 200
    srv_ns, cli_ns = f"castsrv{tag}", f"castcli{tag}"
    srv_if, cli_if = f"vs{tag}", f"vc{tag}"
    srv_ip, cli_ip = f"10.213.{net}.1", f"10.213.{net}.2"
    procs: list[subprocess.Popen[str]] = []
    try:
        _ip("netns", "add", srv_ns)
        _ip("netns", "add", cli_ns)
        _ip("link", "add", srv_if, "type", "veth", "peer", "name", cli_if)
        _ip("link", "set", srv_if, "netns", srv_ns)
        _ip("link", "set", cli_if, "netns", cli_ns)
        for ns, ifname, addr in ((srv_ns, srv_if, srv_ip), (cli_ns, cli_if, cli_ip)):
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", ifname)
            _ip("-n", ns, "link", "set", ifname, "up")
            _ip("-n", ns, "link", "set", "lo", "up")

        config = tmp_path / "system.yaml"
        config.write_text(yaml.safe_dump({"system": "multihost", "subarchitectures": {"vision": {}}}))
        env = dict(os.environ, CAST_SECRET=SECRET, PYTHONPATH=os.pathsep.join([PYTHONPATH, str(COMPONENTS)]))
        server = subprocess.Popen(
            ["ip", "netns", "exec", srv_ns, str(VENV_BIN / "cast"), "serve", str(config), "--listen",
             f"{srv_ip}:0", "--lease-ms", "1500"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=tmp_path,
        )
        procs.append(server)
        assert server.stdout is not None
        first = server.stdout.readline().strip()
        assert first.startswith("listening on "), first
        endpoint = first.removeprefix("listening on ")
        assert endpoint.startswith(srv_ip)
        signer = TokenSigner(SECRET.encode())

        def component(cls: str, cid: str, args: dict[str, object] | None = None) -> Lines:
            cenv = dict(env, CAST_ENDPOINT=endpoint, CAST_COMPONENT_ID=cid, CAST_SUBARCHITECTURE="vision",
                        CAST_TOKEN=signer.issue(Identity(cid, "vision")), CAST_ARGS=json.dumps(args or {}))
            cenv.pop("CAST_SECRET")
            proc = subprocess.Popen(["ip", "netns", "exec", cli_ns, sys.executable, "-m", "cast.run", cls],
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=cenv)
            procs.append(proc)
            return Lines(proc)

        def check(*args: str) -> dict[str, object]:
            token = signer.issue(Identity("checker", "vision"))
            done = subprocess.run(["ip", "netns", "exec", srv_ns, sys.executable, str(COMPONENTS / "netcheck.py"),
                                   endpoint, token, *args], capture_output=True, text=True, env=env, timeout=60)
            return dict(json.loads(done.stdout.strip().splitlines()[-1]))

        watcher = component("rel_components:NetWatcher", "watcher")
        watcher.wait(lambda ls: "WATCHING" in ls, what="the watcher")
        locker = component("rel_components:NetLocker", "locker")
        locker.wait(lambda ls: any(x.startswith("ADOPTED") for x in ls), what="the lock and task")
        writer = component("rel_components:NetWriter", "writer", {"count": 300})
        writer.wait(lambda ls: sum(x.startswith("ACK") for x in ls) >= 50, what="acknowledged writes")

        _ip("-n", srv_ns, "link", "set", srv_if, "down")  # cut the link
        cut_at = time.monotonic()
        released = check("released")  # inside the server's namespace, while the link is down
        time.sleep(max(0.0, 3.0 - (time.monotonic() - cut_at)))  # keep it down a few seconds in all
        _ip("-n", srv_ns, "link", "set", srv_if, "up")
        cut_seconds = time.monotonic() - cut_at
        assert released == {"released": True}

        writer.wait(lambda ls: "DONE" in ls, timeout=120, what="the writer to finish")
        acked = [x.split()[1] for x in writer.lines if x.startswith("ACK")]
        ids_file = tmp_path / "acked.txt"
        ids_file.write_text("\n".join(acked))
        state = check("state", str(ids_file))
        assert state["missing"] == [], state
        top = int(state["revision"])  # type: ignore[call-overload]
        watcher.wait(lambda ls: any(x.startswith(f"EV {top} ") for x in ls), timeout=60, what="the watcher")
        revs = [int(x.split()[1]) for x in watcher.lines if x.startswith("EV")]
        assert revs == list(range(revs[0], top + 1)), "gap or duplicate"
        assert not any(x.startswith("FAILED") for x in watcher.lines)
        record("multihost_link_cut", {"cut_seconds": round(cut_seconds, 2), "acknowledged": len(acked),
                                      "lost": 0, "watcher_events": len(revs), "lease_ms": 1500})
    finally:
        for proc in reversed(procs):
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        for ns in (srv_ns, cli_ns):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
