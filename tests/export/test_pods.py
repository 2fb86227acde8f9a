"""The exported pods' commands work: each container's command line and environment, read back from the manifests,
is run here as a process (the image's /opt/cast and the pod's /var/run/cast mapped to directories of this test, the
Service name to the server's address): a TLS server with client certificates, its health probe, a component's
token init container, its renewing sidecar and the component itself, whose token expires every 3 s while it
writes for 6 s. And `cast token --write/--renew` on its own: what it refuses, and that it renews."""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from cast.auth import TokenSigner
from tests.conftest import SECRET, VENV_BIN, stop_process
from tests.export.helpers import cast, objects, pod_spec, workloads

COMPONENT = '''\
"""Writes COUNT entries, one every EVERY_S seconds, printing each, then stops."""
import time

from google.protobuf.wrappers_pb2 import StringValue

import cast


class Writer(cast.UnmanagedComponent):
    def configure(self, args):
        self.count, self.every = int(args["count"]), float(args["every_s"])

    def run(self):
        for i in range(self.count):
            self.add(f"entry-{i}", StringValue(value=str(i)))
            print(f"wrote entry-{i}", flush=True)
            time.sleep(self.every)
        self.request_stop()
'''

CONFIG = """\
    system: pods
    python_path: [components]
    auth: {token_ttl: 3}
    tls: {ca: certs/ca.pem, cert: certs/server.pem, key: certs/server.key, client_auth: true,
          client_cert: certs/client.pem, client_key: certs/client.key}
    subarchitectures:
      vision:
        components:
          writer: {class: "tiny:Writer", args: {count: 12, every_s: 0.5}}
    """


class Pod:
    """An export's containers run as local processes."""

    def __init__(self, root: Path, out: Path) -> None:
        self.root, self.run_dir = root, root / "run"
        self.workloads = workloads(out)
        self.endpoint = ""
        for secret in (o for o in objects(out) if o["kind"] == "Secret"):
            folder = {"cast-secret": "secret", "cast-tls-client": "tls"}.get(secret["metadata"]["name"])
            for key, value in secret["data"].items() if folder else ():
                (self.run_dir / folder).mkdir(parents=True, exist_ok=True)
                (self.run_dir / folder / key).write_bytes(base64.b64decode(value))

    def here(self, word: str) -> str:
        """A word of a manifest as it is here: the image's checkout, the pod's volumes, the Service's address."""
        word = word.replace("/opt/cast", str(self.root)).replace("/var/run/cast", str(self.run_dir))
        word = word.replace("0.0.0.0:7000", "127.0.0.1:0")  # the server: any free port here
        return word.replace("server-main:7000", self.endpoint).replace("127.0.0.1:7000", self.endpoint)

    def container(self, workload: str, name: str) -> dict[str, Any]:
        pod = pod_spec(self.workloads[workload])
        return next(c for c in [*pod.get("initContainers", []), *pod["containers"]] if c["name"] == name)

    def start(self, workload: str, name: str, argv: Callable[[list[str]], list[str]] = lambda a: a,
              ) -> subprocess.Popen[str]:
        container = self.container(workload, name)
        env = {e["name"]: self.here(e["value"]) for e in container.get("env", [])}
        env["PATH"] = f"{VENV_BIN}{os.pathsep}{os.environ['PATH']}"  # the image's python and cast
        return subprocess.Popen(argv([self.here(w) for w in container["command"]]), env=env, text=True,
                                cwd=self.here(container.get("workingDir", "/opt/cast")),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


@pytest.fixture(scope="module")
def pod(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pod]:
    from tests.reliability.certs import make_ca, make_leaf

    root = tmp_path_factory.mktemp("checkout")
    ca, ca_key, ca_cert = make_ca(root / "certs")
    ca.rename(root / "certs" / "ca.pem")
    # The name components and the probe check is the Service's (server-main); 127.0.0.1 for the test's address.
    for name, client in (("server", False), ("client", True)):
        make_leaf(root / "certs", name, ca_key, ca_cert, dns=("server-main",), client=client)  # NAME.pem, NAME.key
    (root / "components").mkdir()
    (root / "components" / "tiny.py").write_text(COMPONENT)
    (root / "system.yaml").write_text(textwrap.dedent(CONFIG))
    result = cast(root, "export", "system.yaml", "--to", "kubernetes", "-o", "out")
    assert result.code == 0, result.err
    world = Pod(root, root / "out")
    server = world.start("server-main", "server")
    assert server.stdout is not None
    first = server.stdout.readline().strip()
    assert first.startswith("listening on "), first + server.stdout.read()
    world.endpoint = first.removeprefix("listening on ")
    try:
        yield world
    finally:
        stop_process(server, 10)


def test_the_health_probe_over_tls_passes_only_for_the_name_the_components_dial(pod: Pod) -> None:
    probe = pod.container("server-main", "server")["readinessProbe"]["exec"]["command"]
    ok = subprocess.run([pod.here(w) for w in probe], capture_output=True, text=True, timeout=60,
                        env={**os.environ, "PATH": f"{VENV_BIN}{os.pathsep}{os.environ['PATH']}"})
    assert ok.returncode == 0, ok.stderr
    wrong = [pod.here(w) for w in probe]
    wrong[wrong.index("--server-name") + 1] = "server-elsewhere"
    refused = subprocess.run([str(VENV_BIN / "python"), *wrong[1:]], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 1 and "health of" in refused.stderr


def test_the_token_containers_and_the_component_run_with_an_expiring_token(pod: Pod) -> None:
    token = pod.start("writer", "token")
    assert token.wait(60) == 0, token.communicate()[0]
    token_file = pod.run_dir / "token" / "token"
    first = token_file.read_text().strip()
    assert first and (token_file.stat().st_mode & 0o077) == 0
    renewer = pod.start("writer", "token-renewer")
    component = pod.start("writer", "component")
    try:
        assert component.wait(60) == 0, component.communicate()[0]  # 12 writes over 6 s: two token lifetimes
        output = component.communicate()[0]
        assert [line for line in output.splitlines() if line.startswith("wrote ")] == [
            f"wrote entry-{i}" for i in range(12)], output
        assert token_file.read_text().strip() != first  # renewed in place
    finally:
        renewer.send_signal(signal.SIGTERM)
        assert renewer.wait(20) == 0  # a sidecar stopped by the kubelet ends cleanly


def test_cast_token_write_refuses_renew_without_a_ttl_and_writes_only_the_token(tmp_path: Path) -> None:
    (tmp_path / "secret").write_text(f"{SECRET}\n")
    base = ["token", "comp", "--sa", "vision", "--endpoint", "h:1", "--secret-file", str(tmp_path / "secret")]
    refused = cast(tmp_path, *base, "--write", "t", "--renew")
    assert refused.code == 2 and "--renew" in refused.err and "--ttl" in refused.err
    assert not (tmp_path / "t").exists()
    written = cast(tmp_path, *base, "--write", "t", "--privileged", "--ttl", "60")
    assert written.code == 0 and "written to t (expires in 60 s)" in written.out
    identity = TokenSigner(SECRET.encode()).verify((tmp_path / "t").read_text().strip())
    assert tuple(identity) == ("comp", "vision", True)


def test_cast_token_renew_writes_a_fresh_token_every_third_of_its_ttl(tmp_path: Path) -> None:
    (tmp_path / "secret").write_text(f"{SECRET}\n")
    path = tmp_path / "tok"
    renewer = subprocess.Popen([str(VENV_BIN / "cast"), "token", "c", "--sa", "v", "--endpoint", "h:1",
                                "--secret-file", str(tmp_path / "secret"), "--ttl", "1.5", "--write", str(path),
                                "--renew"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen: set[str] = set()
        deadline = time.monotonic() + 30
        while len(seen) < 3 and time.monotonic() < deadline and renewer.poll() is None:
            if path.exists():
                seen.add(path.read_text())
            time.sleep(0.1)
        assert len(seen) >= 3, json.dumps(sorted(seen))
    finally:
        renewer.send_signal(signal.SIGTERM)
        assert renewer.wait(20) == 0, renewer.communicate()[0]
