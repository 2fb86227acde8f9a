"""Every call ends by its deadline, in every language, when the server hangs (docs/client-protocol.md, "Deadlines").

A real ``cast serve`` is stopped with SIGSTOP: its sockets stay open and the kernel still takes bytes,
which is what a deadlocked or swapping server, or a half-open network path, looks like to a client.
Python, C++ and Java clients (tests/interop/stall_client.py, cast_test_stall, cast.itest.Stall; one
connection per call) then make every kind of call at once. Each must end with DeadlineExceededError by
its deadline plus :data:`MARGIN_S`; each client's connection must be dropped by keepalive within
keepalive time + timeout plus :data:`KEEPALIVE_MARGIN_S`. After SIGCONT every connection works again, nothing
acknowledged is lost, and every watcher sees every event once, in order. Timings are printed.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import sys
import time
from pathlib import Path
from typing import Any

import psutil

from tests.conftest import PYTHONPATH, SECRET, ServerHandle, start_server
from tests.interop.child import ChildProcess
from tests.interop.cpp_support import cpp_executable
from tests.interop.java_support import java_classpath

CALL_TIMEOUT_S = 3.0
LOCK_TIMEOUT_S = 1.5
LOCK_MARGIN_S = 1.0  # LOCK_REPLY_MARGIN_S in every library (docs/client-protocol.md, "Deadlines")
KEEPALIVE_S = 10.0 + 5.0  # keepalive time + ping timeout, in every library
MARGIN_S = 1.5  # what a loaded 2-core machine may add to a deadline before the call returns
KEEPALIVE_MARGIN_S = 3.0  # the same for noticing, with the test polling the connections every 0.1 s
KINDS = ("add", "add_async", "overwrite", "delete", "batch", "lock", "try_lock", "unlock", "get", "get_all",
         "exists", "watch", "report")


class StallClient(ChildProcess):
    """One language's stall program: a line per command, JSON lines back."""

    def __init__(self, lang: str, argv: list[str], env: dict[str, str]) -> None:
        self.lang = lang
        self.lines: queue.Queue[dict[str, Any] | None] = queue.Queue()
        super().__init__(lang, argv, env, stdin=True)

    def on_line(self, line: str) -> None:
        """Queue each JSON answer."""
        try:
            self.lines.put(json.loads(line))
        except json.JSONDecodeError:
            pass

    def on_end(self) -> None:
        """No more answers."""
        self.lines.put(None)

    def send(self, command: str) -> None:
        """One command line."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def next(self, timeout: float = 90.0) -> dict[str, Any]:
        """The next answer."""
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"{self.lang}: no answer within {timeout} s\n{self.output()}") from None
        if line is None:
            raise AssertionError(f"{self.lang} exited ({self.proc.wait(10)})\n{self.output()}")
        if "error" in line and "call" not in line and "recovered" not in line:
            raise AssertionError(f"{self.lang} failed: {line}\n{self.output()}")
        return line

    def until(self, key: str) -> list[dict[str, Any]]:
        """The answers up to the one that has ``key``."""
        out = []
        while key not in (line := self.next()):
            out.append(line)
        return out

    def connections(self, port: int) -> set[int]:
        """The local ports of this process's established TCP connections to ``port``."""
        return {c.laddr.port for c in psutil.Process(self.proc.pid).net_connections(kind="tcp")
                if c.raddr and c.raddr.port == port and c.status == psutil.CONN_ESTABLISHED}


def _clients(server: ServerHandle) -> list[StallClient]:
    env = dict(os.environ, CAST_ENDPOINT=server.endpoint, CAST_SECRET=SECRET, PYTHONPATH=PYTHONPATH,
               CAST_STALL_CALL_TIMEOUT_MS=str(round(CALL_TIMEOUT_S * 1000)),
               CAST_STALL_LOCK_TIMEOUT_MS=str(round(LOCK_TIMEOUT_S * 1000)))
    for name in ("CAST_TOKEN", "CAST_TOKEN_FILE", "CAST_RUNTIME_DIR", "CAST_COMPONENT_ID"):
        env.pop(name, None)
    here = Path(__file__).parent
    return [
        StallClient("python", [sys.executable, str(here / "stall_client.py"), "py"], env),
        StallClient("cpp", [str(cpp_executable("cast_test_stall")), "cpp"], env),
        StallClient("java", ["java", "-cp", java_classpath(), "cast.itest.Stall", "java"], env),
    ]


def _deadline(kind: str) -> float:
    return LOCK_TIMEOUT_S + LOCK_MARGIN_S if kind == "lock" else CALL_TIMEOUT_S


def test_every_call_ends_by_its_deadline_on_a_hung_server_and_every_client_recovers(tmp_path: Path) -> None:
    server = start_server(tmp_path, {"system": "stall", "subarchitectures": {"vision": {}}})
    port = int(server.endpoint.rpartition(":")[2])
    clients = _clients(server)
    tool = server.connect("checker", "vision")
    try:
        for c in clients:
            c.next(60)  # ready
        marker = tool.add("marker", _counter(0)).revision  # every watcher sees every event from here on
        acked: list[str] = []
        for c in clients:
            c.send("acked 5")
            acked += c.next()["acked"]
        before = {c.lang: c.connections(port) for c in clients}
        assert all(before.values()), f"a client has no connection to the server: {before}"

        os.kill(server.process.pid, signal.SIGSTOP)
        stopped = time.monotonic()
        for c in clients:
            c.send("stall")
        calls = {c.lang: {line["call"]: line for line in c.until("stalled")} for c in clients}
        dropped: dict[str, float] = {}
        while len(dropped) < len(clients) and time.monotonic() - stopped < KEEPALIVE_S + KEEPALIVE_MARGIN_S + 2:
            for c in clients:
                if c.lang not in dropped and not (before[c.lang] & c.connections(port)):
                    dropped[c.lang] = time.monotonic() - stopped
            time.sleep(0.1)
        stalled_for = time.monotonic() - stopped
        os.kill(server.process.pid, signal.SIGCONT)

        for c in clients:
            c.send("recover")
        recovered = {c.lang: {line["recovered"]: line for line in c.until("recovered_all")} for c in clients}
        final = tool.add("final", _counter(1)).revision
        seen = {}
        for c in clients:
            c.send(f"expect {final}")
            seen[c.lang] = c.next()["revisions"]

        print(f"\nserver stopped for {stalled_for:.1f} s; call timeout {CALL_TIMEOUT_S:g} s, lock timeout "
              f"{LOCK_TIMEOUT_S:g} s (+{LOCK_MARGIN_S:g} s margin)")
        print(f"{'call':10s}" + "".join(f"{lang:>34s}" for lang in calls))
        for kind in KINDS:
            row = "".join(f"{calls[lang][kind]['ms'] / 1000:7.2f} s {calls[lang][kind]['error']!s:24s}"
                          for lang in calls)
            print(f"{kind:10s}{row}")
        print("connection dropped by keepalive after: "
              + ", ".join(f"{lang} {dropped.get(lang, float('nan')):.1f} s" for lang in calls))
        print("after SIGCONT, first successful write: " + ", ".join(
            f"{lang} max {max(r['ms'] for r in recovered[lang].values()) / 1000:.2f} s, "
            f"{max(r['tries'] for r in recovered[lang].values())} tries at most" for lang in calls))

        for lang, by_kind in calls.items():
            assert set(by_kind) == set(KINDS), f"{lang}: calls missing: {set(KINDS) - set(by_kind)}"
            for kind, line in by_kind.items():
                assert line["error"] == "DeadlineExceededError", f"{lang} {kind}: {line}"
                took = line["ms"] / 1000
                assert took <= _deadline(kind) + MARGIN_S, f"{lang} {kind} took {took} s: {line}"
        for c in clients:
            assert c.lang in dropped, (
                f"{c.lang}: its connection to the stopped server was still up {stalled_for:.1f} s later "
                f"(keepalive {KEEPALIVE_S:g} s)\n{c.output()}")
            took = dropped[c.lang]
            assert took <= KEEPALIVE_S + KEEPALIVE_MARGIN_S, f"{c.lang}: dropped after {took:.1f} s"
        for lang, by_kind in recovered.items():
            failed = {kind: line for kind, line in by_kind.items() if "error" in line}
            assert not failed, f"{lang}: connections that did not work again: {failed}"
        missing = [i for i in acked if not tool.exists(i)]
        assert not missing, f"acknowledged writes lost: {missing}"
        for lang, revisions in seen.items():
            later = [r for r in revisions if r >= marker]
            assert later == list(range(marker, final + 1)), (
                f"{lang}: events from revision {marker} to {final} not seen exactly once in order: {later}")
        for c in clients:
            c.send("quit")
            assert c.wait(30) == 0, c.output()
    finally:
        os.kill(server.process.pid, signal.SIGCONT)
        for c in clients:
            if c.proc.poll() is None:
                c.proc.kill()
        tool._cast_close()
        server.stop()


def _counter(value: int) -> Any:
    from cast_testing_pb2 import Counter

    return Counter(writer="checker", value=value)
