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
import time
from pathlib import Path

import yaml

from cast.auth import TokenSigner
from cast.core.records import Identity
from tests.conftest import PYTHONPATH, SECRET, VENV_BIN, wait_for
from tests.netns import Lines, Namespaces, ip, stop_all
from tests.reliability.figures import record

COMPONENTS = Path(__file__).resolve().parent / "components"


def test_link_cut_between_namespaces_loses_nothing_and_releases_the_lost_session(tmp_path: Path) -> None:
    spaces = Namespaces(second_octet=213)
    procs: list[subprocess.Popen[str]] = []
    try:
        srv_ns, cli_ns = spaces.add("srv"), spaces.add("cli")
        srv_ip, _ = spaces.link(srv_ns, cli_ns)
        srv_if = spaces.interfaces[srv_ns]

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
        wait_for(lambda: "WATCHING" in watcher.lines, what="the watcher")
        locker = component("rel_components:NetLocker", "locker")
        wait_for(lambda: any(x.startswith("ADOPTED") for x in locker.lines), what="the lock and task")
        writer = component("rel_components:NetWriter", "writer", {"count": 300})
        wait_for(lambda: sum(x.startswith("ACK") for x in writer.lines) >= 50, what="acknowledged writes")

        ip("-n", srv_ns, "link", "set", srv_if, "down")  # cut the link
        cut_at = time.monotonic()
        released = check("released")  # inside the server's namespace, while the link is down
        time.sleep(max(0.0, 3.0 - (time.monotonic() - cut_at)))  # keep it down a few seconds in all
        ip("-n", srv_ns, "link", "set", srv_if, "up")
        cut_seconds = time.monotonic() - cut_at
        assert released == {"released": True}

        wait_for(lambda: "DONE" in writer.lines, timeout=120, what="the writer to finish")
        acked = [x.split()[1] for x in writer.lines if x.startswith("ACK")]
        ids_file = tmp_path / "acked.txt"
        ids_file.write_text("\n".join(acked))
        state = check("state", str(ids_file))
        assert state["missing"] == [], state
        top = int(state["revision"])  # type: ignore[call-overload]
        wait_for(lambda: any(x.startswith(f"EV {top} ") for x in watcher.lines), timeout=60, what="the watcher")
        revs = [int(x.split()[1]) for x in watcher.lines if x.startswith("EV")]
        assert revs == list(range(revs[0], top + 1)), "gap or duplicate"
        assert not any(x.startswith("FAILED") for x in watcher.lines)
        record("multihost_link_cut", {"cut_seconds": round(cut_seconds, 2), "acknowledged": len(acked),
                                      "lost": 0, "watcher_events": len(revs), "lease_ms": 1500})
    finally:
        stop_all(procs)
        spaces.close()
