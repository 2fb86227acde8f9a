"""Security across hosts: TLS everywhere and expiring tokens, with a server and a component on an agent's host.

Two network namespaces joined by a veth pair on 10.219.x.0/24 made here (tests/netns.py). The
system uses TLS with client certificates (`tls:` with `client_auth`), tokens that expire after 2 s
(`auth.token_ttl`), and mutual TLS to the agent (`hosts.arm.tls`). The agent starts server `far`
(TLS, its start barrier through the directory over TLS) and a component that writes for several
token lifetimes: its token file lives on the agent's host and is renewed through `Agent.Renew`,
and its `CAST_TLS_*` files are the agent's own resolution of `tls:`. Every write arrives; without
renewal the component's calls would be refused after 2 s. A test that cannot make namespaces
fails with the reason.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import yaml

from tests.netns import two_hosts
from tests.reliability.certs import make_ca, make_leaf

SLOW = '''\
import os
import time

from google.protobuf.wrappers_pb2 import Int64Value

import cast


class SlowWriter(cast.UnmanagedComponent):
    """Adds <id>-0 .. <id>-<count-1> to SA sa, one each pause seconds (several token lifetimes in all)."""

    def configure(self, args):
        self.sa, self.count, self.pause = args["sa"], int(args["count"]), float(args["pause"])

    def start(self):
        names = ("CAST_TOKEN_FILE", "CAST_TLS_CA", "CAST_TLS_CERT")
        print("ENV " + self.component_id + " " + " ".join(f"{n}={os.environ.get(n, '')}" for n in names), flush=True)

    def run(self):
        for i in range(self.count):
            self.add(f"{self.component_id}-{i}", Int64Value(value=i), subarchitecture=self.sa)
            time.sleep(self.pause)
        print(f"DONE {self.component_id}", flush=True)
        self.wait_for_stop()
'''
COUNT = 24
PAUSE = 0.25  # 24 x 0.25 s = 6 s: three lifetimes of a 2 s token


def test_tls_and_expiring_tokens_reach_a_server_and_a_component_on_another_host(tmp_path: Path) -> None:
    with two_hosts(tmp_path, second_octet=219) as hosts:
        root = hosts.root
        (root / "comps").mkdir()
        (root / "comps" / "slow_components.py").write_text(SLOW)
        # One CA: the servers' and the agent's certificate names both hosts' addresses; one client certificate
        # serves the components (tls.client_cert) and the orchestrator towards the agent (hosts.arm.tls).
        _, ca_key, ca_cert = make_ca(root / "pki")
        make_leaf(root / "pki", "server", ca_key, ca_cert, addresses=(hosts.orch_ip, hosts.agent_ip))
        make_leaf(root / "pki", "client", ca_key, ca_cert, client=True)
        hosts.start_agent("--tls-cert", "pki/server.pem", "--tls-key", "pki/server.key", "--tls-ca",
                          "pki/cast-test-ca.pem")

        def slow(host: str | None, sa: str) -> dict[str, object]:
            return {"class": "slow_components:SlowWriter", **({"host": host} if host else {}), "privileged": True,
                    "restart": "never", "args": {"sa": sa, "count": COUNT, "pause": PAUSE}}

        (root / "system.yaml").write_text(yaml.safe_dump({
            "system": "mhsecure",
            "python_path": ["comps"],
            "hosts": {"arm": {"agent": hosts.agent_endpoint,
                              "tls": {"ca": "pki/cast-test-ca.pem", "cert": "pki/client.pem",
                                      "key": "pki/client.key"}}},
            "tls": {"ca": "pki/cast-test-ca.pem", "cert": "pki/server.pem", "key": "pki/server.key",
                    "client_auth": True, "client_cert": "pki/client.pem", "client_key": "pki/client.key"},
            "auth": {"token_ttl": 2},
            "servers": {
                "main": {"listen": f"{hosts.orch_ip}:0", "subarchitectures": ["near"]},
                "far": {"listen": f"{hosts.agent_ip}:0", "host": "arm", "subarchitectures": ["far"]},
            },
            "orchestrator": {"lease_ms": 3000, "stop_timeout": 5, "connect_timeout": 60},
            "subarchitectures": {
                "near": {"components": {"lslow": slow(None, "far")}},
                "far": {"components": {"rslow": slow("arm", "near")}},
            },
        }, sort_keys=False))

        check = hosts.cast("check", "system.yaml", "--probe")
        assert check.returncode == 0, check.stdout + check.stderr

        run, out = hosts.start_run("system.yaml", "--no-status", "--runtime-dir", "rt", "--summary-json",
                                   "summary.json")
        out.wait("server far on host arm: listening on")
        out.wait("all 2 components started in")
        env_line = out.wait("ENV rslow ")
        values = dict(item.split("=", 1) for item in env_line.split("ENV rslow ", 1)[1].split())
        # The token file is the agent's (not <runtime dir>/tokens on the orchestrator's host); the TLS files
        # are the agent's resolution of tls: under its --root.
        assert values["CAST_TOKEN_FILE"] and "/rt/tokens/" not in values["CAST_TOKEN_FILE"], env_line
        assert values["CAST_TLS_CA"] == str((root / "pki" / "cast-test-ca.pem").resolve()), env_line
        assert values["CAST_TLS_CERT"] == str((root / "pki" / "client.pem").resolve()), env_line
        for cid in ("rslow", "lslow"):
            out.wait(f"DONE {cid}", timeout=90)

        for sa, writer in (("near", "rslow"), ("far", "lslow")):
            listed = hosts.cast("ls", sa, "--json", "--runtime-dir", "rt")
            assert listed.returncode == 0, listed.stderr
            rows = json.loads(listed.stdout)
            ids = {r["id"] for r in rows} if isinstance(rows, list) else set(rows)
            assert {f"{writer}-{i}" for i in range(COUNT)} <= ids, (sa, sorted(ids))

        run.send_signal(signal.SIGINT)
        code = run.wait(60)
        assert code == 0, "\n".join(out.lines[-200:])  # a killed component's stacks are among them
        summary = json.loads((root / "summary.json").read_text())
        assert summary["failures"] == []
        assert not any("UNAUTHENTICATED" in line for line in out.lines), "\n".join(out.lines[-40:])
        hosts.wait_agent_alone()
        renewed = [line for line in out.lines if "cannot renew" in line]
        assert not renewed, renewed
        print(f"\n{COUNT} writes each way over {COUNT * PAUSE:.1f} s with 2 s tokens, TLS on every link")


def test_a_remote_server_that_ends_stops_the_system(tmp_path: Path) -> None:
    with two_hosts(tmp_path, second_octet=219) as hosts:
        hosts.start_agent()
        (hosts.root / "system.yaml").write_text(yaml.safe_dump({
            "system": "mhserverdies",
            "hosts": {"arm": hosts.agent_endpoint},
            "servers": {
                "main": {"listen": f"{hosts.orch_ip}:0", "subarchitectures": ["near"]},
                "far": {"listen": f"{hosts.agent_ip}:0", "host": "arm", "subarchitectures": ["far"]},
            },
            "orchestrator": {"lease_ms": 3000, "stop_timeout": 5},
            "subarchitectures": {"near": {}, "far": {}},
        }, sort_keys=False))
        run, out = hosts.start_run("system.yaml", "--no-status", "--runtime-dir", "rt", "--summary-json",
                                   "summary.json")
        line = out.wait("server far on host arm: listening on")
        out.wait("started in")
        pid_of_far = _pid_listening(hosts.agent_ns, line.split("listening on ", 1)[1].split(",")[0])
        killed_at = time.monotonic()
        os.kill(pid_of_far, signal.SIGKILL)
        ended = out.wait("server far on host arm ended")
        assert "its SAs (far) are gone, so the system stops" in ended and "signal 9" in ended, ended
        code = run.wait(60)
        assert code != 0, "\n".join(out.lines[-30:])
        summary = json.loads((hosts.root / "summary.json").read_text())
        assert any("server far on host arm" in f for f in summary["failures"]), summary["failures"]
        hosts.wait_agent_alone()
        print(f"\nremote server killed: system stopped, exit {code}, {time.monotonic() - killed_at:.2f} s")


def _pid_listening(ns: str, endpoint: str) -> int:
    """The pid of the process listening on ``endpoint`` in namespace ``ns`` (``ss -ltnp``)."""
    port = endpoint.rpartition(":")[2]
    done = subprocess.run(["ip", "netns", "exec", ns, "ss", "-ltnpH", f"sport = :{port}"], capture_output=True,
                          text=True, check=True)
    return int(done.stdout.split("pid=", 1)[1].split(",", 1)[0])
