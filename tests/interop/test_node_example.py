"""The Node.js example (examples/node): a fourth language speaking the gRPC API, checked from Python.

It runs against a real `cast serve` with the launch contract, as `cast run` would start it, and
inside `cast run` of the example's own system (`language: other`) next to its Python reactor. The
Node runtime, the packages and the schema file come from `make node` (a `make test` step): when they
are missing these tests fail, they never skip.
"""

from __future__ import annotations

import json
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.wrappers_pb2 import StringValue

from cast.core.records import Identity
from tests.conftest import SECRET, ServerHandle, renewing_token_file
from tests.orchestrator.conftest import start_cast_run, wait_for
from tests.reliability.conftest import serve_tls

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "node"
CAST = str(Path(sys.executable).parent / "cast")


def node() -> str:
    """The node executable, with the example's packages and schema in place; fails the test otherwise."""
    found = shutil.which("node")
    if found is None:
        pytest.fail("node is not installed: run `make node` (it installs Debian's nodejs and npm)")
    for needed in (EXAMPLE / "node_modules" / "@grpc" / "grpc-js", EXAMPLE / "generated" / "entry-types.binpb"):
        if not needed.exists():
            pytest.fail(f"{needed} is missing: run `make node` (npm ci and the schema file)")
    return found


class NodeComponent:
    """examples/node/component.js started with a launch environment; its lines are collected as printed."""

    def __init__(self, env: dict[str, str]) -> None:
        self.proc = subprocess.Popen([node(), str(EXAMPLE / "component.js")], env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.errors: list[str] = []
        self._new: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._pump, args=(self.proc.stdout, self.lines, True), daemon=True).start()
        threading.Thread(target=self._pump, args=(self.proc.stderr, self.errors, False), daemon=True).start()

    def _pump(self, stream: Any, into: list[str], notify: bool) -> None:
        for line in stream:
            into.append(line.rstrip("\n"))
            if notify:
                self._new.put(line)

    def output(self) -> str:
        """Everything printed so far, for failure messages."""
        return "\n".join([*self.lines, "--- stderr ---", *self.errors])

    def step(self, name: str) -> list[str]:
        """The texts of the lines of one step ("added: X" -> "X")."""
        return [line.split(": ", 1)[1] for line in self.lines if line.startswith(f"{name}: ")]

    def wait_line(self, prefix: str, timeout: float = 60.0) -> str:
        """The first line starting with ``prefix``, waiting for it if need be."""
        deadline = time.monotonic() + timeout
        while True:
            hit = next((line for line in self.lines if line.startswith(prefix)), None)
            if hit is not None:
                return hit
            if self.proc.poll() is not None and self._new.empty():
                raise AssertionError(f"node exited ({self.proc.returncode}) without '{prefix}'\n{self.output()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"no line '{prefix}' from node\n{self.output()}")
            try:
                self._new.get(timeout=0.1)
            except queue.Empty:
                pass

    def wait(self, timeout: float = 60.0) -> int:
        """The exit status."""
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"node did not exit\n{self.output()}") from None
        time.sleep(0.05)  # let the readers take the last lines
        return code

    def close(self) -> None:
        """Kill it if it still runs (test clean-up)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def run_node(env: dict[str, str], timeout: float = 60.0) -> tuple[int, NodeComponent]:
    component = NodeComponent(env)
    try:
        return component.wait(timeout), component
    finally:
        component.close()


def cli(server: ServerHandle, *args: str) -> Any:
    """`cast ARGS --endpoint ... --json` against the server, as a tool."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    out = subprocess.run([CAST, *args, "--endpoint", server.endpoint, "--json"], env={**env, "CAST_SECRET": SECRET},
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_node_component_registers_writes_watches_and_completes_a_task(server: ServerHandle) -> None:
    code, nodejs = run_node(server.env("greeter", "vision", args={"count": 2, "text": "hi from node"}))
    assert code == 0, nodejs.output()
    steps = [line.split(":", 1)[0] for line in nodejs.lines]
    assert steps[:5] == ["contract", "system", "registered", "schemas", "watching"], nodejs.output()
    assert steps[-5:] == ["adopted", "read", "completed", "done", "stopped"], nodejs.output()
    assert steps.index("proposed") > max(i for i, s in enumerate(steps) if s in ("added", "saw"))
    assert "google.protobuf.StringValue among them" in nodejs.step("schemas")[0]
    ids = [text.split()[0] for text in nodejs.step("added")]
    assert len(ids) == 2
    # The watch brought each add back, with the entry (decoded in Node).
    for n, entry_id in enumerate(ids, 1):
        assert any(s.startswith(f"ADD {entry_id} by greeter ") and s.endswith(f'"hi from node #{n}"')
                   for s in nodejs.step("saw")), nodejs.output()
    # Python reads what Node wrote.
    reader = server.connect("reader", "vision")
    try:
        entries = {e.id: e for e in reader.get_all(StringValue)}
        assert sorted(entries) == sorted(ids)
        assert [entries[i].value.value for i in ids] == ["hi from node #1", "hi from node #2"]
        assert {entries[i].author for i in ids} == {"greeter"}
    finally:
        reader._cast_close()
    # The task went through the vision task manager: proposed, adopted, completed.
    task = nodejs.step("proposed")[0].split()[1]
    assert nodejs.step("adopted") == [f"task {task}"] and nodejs.step("completed") == [f"task {task} (SUCCEEDED)"]
    vision = next(sa for sa in cli(server, "tasks")["subarchitectures"] if sa["subarchitecture"] == "vision")
    assert (vision["proposed"], vision["adopted"], vision["completed"], vision["rejected"]) == (1, 1, 1, 0)
    info = next(c for c in cli(server, "components") if c["id"] == "greeter")
    assert (info["language"], info["kind"], info["sessions"]) == ("node", "managed", 1)


def test_node_task_waits_for_its_decision_on_the_decisions_stream(server_factory: Any) -> None:
    import cast

    server = server_factory({"system": "fifo", "subarchitectures": {
        "vision": {"task_manager": {"policy": "fifo", "max_concurrent": 1}}}})

    class Holder(cast.ManagedComponent):
        def start(self) -> None:
            self.adopted = threading.Event()

        def task_adopted(self, task: cast.Task) -> None:
            self.task = task
            self.adopted.set()

    holder = server.connect("holder", "vision", cls=Holder)
    nodejs = NodeComponent(server.env("greeter", "vision"))
    try:
        holder.start()
        holder.propose_task("hold-the-slot")
        assert holder.adopted.wait(15)
        proposed = nodejs.wait_line("proposed: ")
        assert proposed.endswith("(TASK_STATE_WAITING)"), nodejs.output()  # the only slot is taken
        assert not nodejs.step("adopted")
        holder.task_complete(holder.task)
        assert nodejs.wait() == 0, nodejs.output()
        task = proposed.split()[2]
        assert nodejs.step("adopted") == [f"task {task}"] and nodejs.step("completed") == [f"task {task} (SUCCEEDED)"]
    finally:
        holder._cast_close()
        nodejs.close()


def test_node_sends_the_renewed_token_from_its_token_file(server: ServerHandle, tmp_path: Path) -> None:
    """Tokens living 2 s, renewed in CAST_TOKEN_FILE: the Node component keeps writing well past the first
    one's expiry. The same component with a fixed short-lived token is refused once it has expired."""
    args = {"stay": True, "every": 0.2}
    with renewing_token_file(server.signer, Identity("renewed", "vision"), tmp_path / "renewed.token") as path:
        env = server.env("renewed", "vision", args=args)
        del env["CAST_TOKEN"]  # the file alone
        env["CAST_TOKEN_FILE"] = str(path)
        nodejs = NodeComponent(env)
        try:
            nodejs.wait_line("done: ")
            first_expiry = time.time() + 2.0  # the token read at start-up was issued before this moment
            wait_for(lambda: time.time() > first_expiry + 1.5 or nodejs.proc.poll() is not None, 30, "expiry")
            before = len(nodejs.step("added"))
            wait_for(lambda: len(nodejs.step("added")) >= before + 3 or nodejs.proc.poll() is not None, 30,
                     "writes with renewed tokens")
            assert nodejs.proc.poll() is None, nodejs.output()
            nodejs.proc.send_signal(signal.SIGTERM)
            assert nodejs.wait() == 0, nodejs.output()
            assert nodejs.lines[-1] == "stopped: exit code 0"
        finally:
            nodejs.close()
    fixed = server.env("fixed", "vision", args=args)
    fixed["CAST_TOKEN"] = server.signer.issue(Identity("fixed", "vision"), ttl_seconds=3)
    code, nodejs = run_node(fixed)
    assert code == 1, nodejs.output()
    assert "UNAUTHENTICATED" in nodejs.errors[-1] and "expired" in nodejs.errors[-1], nodejs.output()


def test_node_speaks_tls_with_a_client_certificate(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki, client_auth=True)
    try:
        env = handle.env("secure", "vision")
        env.update(CAST_TLS_CA=str(pki["ca"]), CAST_TLS_CERT=str(pki["client_cert"]),
                   CAST_TLS_KEY=str(pki["client_key"]))
        code, nodejs = run_node(env)
        assert code == 0, nodejs.output()
        assert "(TLS)" in nodejs.lines[0]
        # Without a client certificate the server refuses the connection.
        del env["CAST_TLS_CERT"], env["CAST_TLS_KEY"]
        code, nodejs = run_node(env)
        assert code == 1 and "UNAVAILABLE" in nodejs.errors[-1], nodejs.output()
        env["CAST_TLS_CERT"] = str(pki["client_cert"])  # without its key
        code, nodejs = run_node(env)
        assert code == 2 and "set CAST_TLS_CERT and CAST_TLS_KEY together" in nodejs.errors[-1], nodejs.output()
    finally:
        handle.stop()


def test_node_names_what_is_missing_from_its_launch_contract(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    code, nodejs = run_node({**env, "CAST_ENDPOINT": "127.0.0.1:1"})
    assert code == 2
    assert nodejs.errors == ["error: missing launch environment: CAST_COMPONENT_ID, CAST_SUBARCHITECTURE, CAST_TOKEN "
                             "or CAST_TOKEN_FILE; start the component with `cast run CONFIG`, or set the variables "
                             "`cast token` prints"]
    empty = tmp_path / "empty.token"
    empty.write_text(" \n")
    code, nodejs = run_node({**env, "CAST_ENDPOINT": "127.0.0.1:1", "CAST_COMPONENT_ID": "c",
                             "CAST_SUBARCHITECTURE": "vision", "CAST_TOKEN": "stale", "CAST_TOKEN_FILE": str(empty)})
    assert code == 2
    assert nodejs.errors == [f"error: CAST_TOKEN_FILE names {empty}, which is empty: point it at a token file "
                             "(`cast run` renews one per component), or unset it"], nodejs.output()


def test_the_example_system_runs_node_next_to_python(tmp_path: Path) -> None:
    node()
    # From another directory: `run: node component.js` is relative to the configuration file.
    run = start_cast_run(tmp_path, EXAMPLE / "system.yaml", "--summary-json", str(tmp_path / "summary.json"))
    try:
        wait_for(lambda: "by reactor" in run.output() and "greeter | completed: task" in run.output(), 60,
                 "the reactor's reply to reach the Node component")
    finally:
        code = run.stop()
    out = run.output()
    assert code == 0, out
    assert "reactor | python read greeter-" in out
    assert "greeter | saw: ADD reply-greeter-" in out and "by reactor" in out
    assert "every component ran and stopped cleanly" in out
    # Under `cast run` the Node component waits at the start barrier too, between its watch and its first write.
    assert out.index("greeter | watching:") < out.index("greeter | released:") < out.index("greeter | added:"), out
    summary = json.loads((tmp_path / "summary.json").read_text())
    greeter = next(c for c in summary["components"] if c["id"] == "greeter")
    assert (greeter["language"], greeter["sessions"]) == ("node", 1)
    greetings = next(sa for sa in summary["subarchitectures"] if sa["name"] == "greetings")
    assert greetings["counters"]["completed"] == 1


def test_readme_shows_the_example_as_it_is() -> None:
    readme = (ROOT / "README.md").read_text()
    start = readme.index("## Components in other languages\n")
    section = readme[start:readme.index("\n## ", start + 1)]
    commands = [line.split("#")[0].strip() for line in re.findall(r"```sh\n(.*?)```", section, re.S)[0].splitlines()]
    assert commands == ["make node", "cast run examples/node/system.yaml --for 10"]
    yaml_block = re.findall(r"```yaml\n(.*?)```", section, re.S)[0]
    assert yaml_block in (EXAMPLE / "system.yaml").read_text()
