"""A `cast agent` subprocess on port 0, a root with a configuration and Python components, an Attach client.

Shared by the tests and by the orchestrator stand-in (tests/agent/standin.py), which imports
only this module and the generated stubs.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc

from cast.auth import TokenSigner
from cast.core.records import Identity
from cast.testing import wait_for
from cast.v1 import agent_pb2, agent_pb2_grpc
from tests.conftest import stop_process

ROOT = Path(__file__).resolve().parents[2]
VENV_BIN = Path(sys.executable).parent
SECRET = "agent-test-secret-0123456789abcdef-0123456789"
SYSTEM = "agenttest"
CONFIG = "system.yaml"

COMPONENTS = '''\
"""Components the agent tests launch."""

import sys
import time

from cast import UnmanagedComponent


class Chatty(UnmanagedComponent):
    """Prints a few lines (one on stderr) and ends."""

    def run(self) -> None:
        for i in range(3):
            print(f"chatty line {i}", flush=True)
        print("chatty on stderr", file=sys.stderr, flush=True)
        self.request_stop()  # after run() a component serves callbacks until asked to stop


class Sleeper(UnmanagedComponent):
    """Runs until stopped; stops at once."""

    def start(self) -> None:
        print("sleeper started", flush=True)


class Stubborn(UnmanagedComponent):
    """Runs until stopped; its stop() hangs."""

    def start(self) -> None:
        print("stubborn started", flush=True)

    def stop(self) -> None:
        time.sleep(600)
'''

CONFIG_TEXT = f'''\
system: {SYSTEM}
python_path: [components]
subarchitectures:
  sa:
    components:
      chatty: {{class: "agent_components:Chatty"}}
      sleeper: {{class: "agent_components:Sleeper"}}
      stubborn: {{class: "agent_components:Stubborn"}}
      ghost: {{class: "no_such_module:Ghost"}}
      native: {{language: cpp, run: ./bin/not-built}}
'''


def make_root(root: Path) -> Path:
    """A root holding the configuration and the components module; returns ``root``."""
    (root / "components").mkdir(parents=True, exist_ok=True)
    (root / "components" / "agent_components.py").write_text(COMPONENTS)
    (root / CONFIG).write_text(CONFIG_TEXT)
    (root / "secret").write_text(SECRET + "\n")
    return root


def orchestrator_token(secret: str = SECRET, component_id: str = "orchestrator", privileged: bool = True) -> str:
    """The token an orchestrator presents to an agent."""
    return TokenSigner(secret.encode()).issue(Identity(component_id, "", privileged))


def metadata(token: str | None = None) -> tuple[tuple[str, str], ...]:
    """Call metadata carrying ``token`` (default: the orchestrator's)."""
    return (("authorization", f"Bearer {token or orchestrator_token()}"),)


@dataclass
class AgentHandle:
    """A `cast agent` process."""

    process: subprocess.Popen[str]
    endpoint: str
    first_line: str
    output: list[str] = field(default_factory=list)

    def channel(self, credentials: grpc.ChannelCredentials | None = None) -> grpc.Channel:
        """A channel to the agent."""
        if credentials is not None:
            return grpc.secure_channel(self.endpoint, credentials)
        return grpc.insecure_channel(self.endpoint)

    def stop(self) -> None:
        """SIGTERM, then SIGKILL."""
        stop_process(self.process, 15)


def start_agent(root: Path, *extra: str, secret: bool = True, tmpdir: Path | None = None) -> AgentHandle:
    """`cast agent --listen 127.0.0.1:0 --root ROOT [--secret-file ROOT/secret] EXTRA...`, once it listens.

    ``tmpdir``: the agent's TMPDIR (where it keeps the token files it writes).
    """
    args = [str(VENV_BIN / "cast"), "agent", "--listen", "127.0.0.1:0", "--root", str(root), *extra]
    if secret:
        args += ["--secret-file", str(root / "secret")]
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    if tmpdir is not None:
        env["TMPDIR"] = str(tmpdir)
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=root)
    assert proc.stdout is not None
    first = proc.stdout.readline().strip()
    if not first.startswith("cast agent listening on "):
        proc.kill()
        raise RuntimeError(f"the agent did not start: {first}\n{proc.stdout.read()}")
    endpoint = first.removeprefix("cast agent listening on ").split()[0]
    handle = AgentHandle(proc, endpoint, first)

    def drain() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            handle.output.append(line)

    threading.Thread(target=drain, daemon=True).start()
    return handle


class Attachment:
    """An orchestrator's Attach stream, in a thread: keepalives (with acks) out, events collected."""

    def __init__(self, channel: grpc.Channel, system: str = SYSTEM, lease_ms: int = 3000, grace_ms: int = 1000,
                 token: str | None = None, ack_seq: int = 0) -> None:
        self.events: list[agent_pb2.AgentEvent] = []
        self.error: grpc.RpcError | None = None
        self._out: queue.Queue[agent_pb2.AttachRequest | None] = queue.Queue()
        self._out.put(agent_pb2.AttachRequest(system=system, lease_ms=lease_ms, grace_ms=grace_ms, ack_seq=ack_seq))
        self._lock = threading.Lock()
        self._period = lease_ms / 3000
        self._closed = threading.Event()
        self._call = agent_pb2_grpc.AgentStub(channel).Attach(self._requests(), metadata=metadata(token))
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._keepalive, daemon=True).start()
        self.wait(lambda: self.of("attached") or self.error, what="the attached event")

    def _requests(self) -> Iterator[agent_pb2.AttachRequest]:
        while True:
            request = self._out.get()
            if request is None:
                return
            yield request

    def _keepalive(self) -> None:
        while not self._closed.wait(self._period):
            self._out.put(agent_pb2.AttachRequest(ack_seq=self.last_seq))

    def _read(self) -> None:
        try:
            for event in self._call:
                with self._lock:
                    self.events.append(event)
        except grpc.RpcError as exc:
            self.error = exc
        finally:
            self._closed.set()

    @property
    def last_seq(self) -> int:
        """The highest seq received."""
        with self._lock:
            return max((e.seq for e in self.events), default=0)

    def of(self, kind: str, component_id: str | None = None) -> list[Any]:
        """The events of one kind ("output", "exit", "resources", "attached"), optionally of one component."""
        with self._lock:
            found = [getattr(e, kind) for e in self.events if e.WhichOneof("event") == kind]
        return [f for f in found if component_id is None or getattr(f, "component_id", None) == component_id]

    def wait(self, condition: Callable[[], Any], timeout: float = 30.0, what: str = "events") -> Any:
        """Poll ``condition`` until truthy (cast.testing.wait_for: a guard timeout, not a measurement); the
        failure lists the events so far."""
        def seen() -> Any:
            value = condition()
            assert value, f"events: {self.events}; error: {self.error}"
            return value

        return wait_for(seen, timeout, what)

    def close(self) -> None:
        """End the request stream (the orchestrator goes away cleanly)."""
        self._closed.set()
        self._out.put(None)

    def cancel(self) -> None:
        """Drop the stream at once (as a cut link)."""
        self._closed.set()
        self._call.cancel()


def launch_request(component_id: str, server_endpoint: str, server_secret: str, system: str = SYSTEM,
                   config: str = CONFIG) -> agent_pb2.LaunchRequest:
    """A Launch of one component of the test configuration, with the launch contract for ``server_endpoint``."""
    signer = TokenSigner(server_secret.encode())
    env = {
        "CAST_ENDPOINT": server_endpoint,
        "CAST_COMPONENT_ID": component_id,
        "CAST_SUBARCHITECTURE": "sa",
        "CAST_TOKEN": signer.issue(Identity(component_id, "sa")),
        "CAST_ARGS": json.dumps({}),
    }
    return agent_pb2.LaunchRequest(system=system, config_path=config, component_id=component_id, env=env)
