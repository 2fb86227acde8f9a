"""The C++ and Java clients under failures, written once: server restarts (resume without gap, or the
resync signal), a cut connection, a stuck watcher, TLS from the launch contract, and tokens renewed
through CAST_TOKEN_FILE. test_cpp_reliability.py and test_java_reliability.py run them per language."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter, Pose

from cast.core.records import Identity
from cast.v1 import directory_pb2
from tests.conftest import ServerHandle, renewing_token_file
from tests.interop.probes import COUNTER, DRIVERS, counter_json, local_type, run_script, start, vision_ops
from tests.interop.restart_support import restart_config, write_until
from tests.reliability.conftest import kill9, serve, serve_tls, wait_for
from tests.reliability.proxy import Proxy


def _revisions(events: list[dict[str, Any]]) -> list[int]:
    # Java prints revisions as numbers, C++ too; int() also takes int64 strings, should either change.
    return [int(e["revision"]) for e in events if e["sa"] == "vision"]


class _Restarted:
    """A one-server system with a probe watching vision and a Python writer, whose server can be
    killed and started again on the same port (the clients reconnect to the address they know)."""

    def __init__(self, lang: str, tmp_path: Path, component: str, persistence: bool) -> None:
        self.config = restart_config(tmp_path, persistence=persistence)
        self.server = serve(self.config)
        self.port = self.server.endpoint.rpartition(":")[2]
        self.probe = start(lang, self.server.env(component, "vision"))
        self.writer: Any = None

    def begin(self, first: int) -> Any:
        """Watch, write ``first`` entries and see them all; the watch."""
        self.probe.ready()
        watch = self.probe.watch(vision_ops())
        self.writer = self.server.connect("writer", "vision")
        write_until(self.writer, "a", first)
        assert _revisions(self.probe.watch_events(watch, first, 20000)) == list(range(1, first + 1))
        return watch

    def serve_again(self) -> None:
        """Start the killed server again, at the same address."""
        self.server = serve(self.config, listen=f"127.0.0.1:{self.port}")

    def close(self) -> None:
        """Stop everything (test clean-up)."""
        if self.writer is not None:
            self.writer._cast_close()
        self.probe.close()
        self.server.stop()


@contextmanager
def _restarted(
    lang: str, tmp_path: Path, component: str, persistence: bool, first: int
) -> Iterator[tuple[_Restarted, Any]]:
    """A :class:`_Restarted` rig past :meth:`_Restarted.begin`, and its watch; closed on the way out."""
    rig = _Restarted(lang, tmp_path, component, persistence)
    try:
        yield rig, rig.begin(first)
    finally:
        rig.close()


def watch_resumes_after_a_server_restart(lang: str, tmp_path: Path, component: str) -> None:
    """A watch resumes with no gap and no duplicate across a journaled server's restart."""
    with _restarted(lang, tmp_path, component, persistence=True, first=50) as (rig, watch):
        probe = rig.probe
        kill9(rig.server)
        # While the server is away a call fails promptly with a clear error; it does not hang.
        started = time.monotonic()
        err = probe.fails("UnavailableError", "get", timeout=40, id="a-0", type=COUNTER)
        assert "unavailable" in err["message"] and "retry" in err["message"], err
        assert time.monotonic() - started < 35
        rig.serve_again()
        write_until(rig.writer, "b", 50)
        top = rig.writer.get_entry("b-49", Counter).revision
        assert _revisions(probe.watch_events(watch, top, 30000)) == list(range(1, top + 1)), "gap or duplicate"
        assert probe.failure(watch, within=0.5) is None
        # The component registered with the new server process (which knew nothing of its old
        # session), and reads and writes again.
        running = directory_pb2.COMPONENT_STATE_RUNNING
        wait_for(lambda: (i := rig.server.components().get(component)) is not None and i.state == running
                 and i.session_id != "", timeout=30, what="re-registration")
        assert probe.ok("get", id="b-0", type=COUNTER)["value"] == {}
        probe.ok("add", id="after", type=COUNTER, value=counter_json(component, 1))
        assert probe.quit() == 0


def restart_without_history_gives_the_resync_signal(lang: str, tmp_path: Path, component: str) -> None:
    """A server restarted with no journal tells the watcher to resynchronise instead of mixing histories."""
    with _restarted(lang, tmp_path, component, persistence=False, first=5) as (rig, watch):
        probe = rig.probe
        kill9(rig.server)
        rig.serve_again()
        # The new server starts at revision 0 again: resuming at 6 would silently mix two histories.
        write_until(rig.writer, "b", 10)
        failed = probe.failure(watch, within=30)
        assert failed is not None and failed["error"] == "HistoryExpiredError", "not told to resynchronise"
        # Only Java's watch_failed event carries the message (the C++ probe reports the error's name).
        assert "message" not in failed or "resynchronise" in failed["message"], failed
        assert _revisions(probe.watch_events(watch)) == [1, 2, 3, 4, 5], "nothing from the other history"
        assert probe.active(watch) in (False, None)
        # Resynchronising: read the state, watch again.
        assert len(probe.ok("get_all", type=COUNTER)["entries"]) == 10
        again = probe.watch(vision_ops())
        rig.writer.add("c", Counter(value=1))
        assert len(_revisions(probe.watch_events(again, 1, 10000))) == 1
        assert probe.quit() == 0


def cut_connection_releases_locks_and_the_watch_catches_up(lang: str, server: ServerHandle, component: str) -> None:
    """A connection cut by a proxy ends the session (locks released); the watch catches up without a gap."""
    proxy = Proxy(server.endpoint)
    env = server.env(component, "vision")
    env["CAST_ENDPOINT"] = proxy.endpoint
    probe = start(lang, env)
    other = server.connect("other", "vision")
    try:
        probe.ready()
        probe.ok("add", id="doc", type=COUNTER, value=counter_json(component, 1))
        watch = probe.watch(vision_ops())
        probe.ok("lock", id="doc", mode="OD")
        assert not other.try_lock("doc")
        proxy.cut()
        # The server notices the broken streams, ends the session and releases the lock.
        wait_for(lambda: other.try_lock("doc"), timeout=30, what="the lock to be released")
        other.unlock("doc")
        for i in range(20):
            other.add(f"while-cut-{i}", Counter(value=i))
        proxy.restore()
        top = other.get_entry("while-cut-19", Counter).revision
        revs = _revisions(probe.watch_events(watch, top - 1, 30000))  # every change after the add of "doc" (revision 1)
        assert revs == list(range(2, top + 1)), "the watcher caught up with no gap and no duplicate"
        assert probe.failure(watch, within=0) is None
        wait_for(lambda: server.components()[component].sessions >= 2, timeout=30, what="re-registration")
        # Locks do not survive a disconnect: the holder must take it again.
        assert probe.ok("lock", id="doc", mode="OD", timeout_ms=10000)["depth"] == 1
        assert not other.try_lock("doc")
        assert probe.quit() == 0
    finally:
        other._cast_close()
        probe.close()
        proxy.close()


def stuck_watcher_never_blocks_writers(lang: str, server_factory: Any, component: str) -> None:
    """A watcher whose callback is stuck never holds up writers, and is told when it falls past the history."""
    server = server_factory({"system": "lag", "limits": {"history_events": 64}, "subarchitectures": {"vision": {}}})
    env = server.env(component, "vision")
    # Few undelivered events may wait in the client, so the stuck callback backs up into the server.
    env[DRIVERS[lang].max_pending_env] = "4"
    probe = start(lang, env)
    py = server.connect("pyfast", "vision")
    try:
        probe.ready()
        watch = probe.watch(local_type("cast.testing.Pose", include_entry=True), gated=True)
        # Far more than the history, in events and in bytes (past the transport's buffers), while
        # the callback is stuck: the writer is never held up.
        label = "x" * 2048
        started = time.monotonic()
        for i in range(3000):
            py.add(f"p{i}", Pose(x=i, label=label))
        assert time.monotonic() - started < 60
        probe.ok("open_gate")
        failed = probe.failure(watch, within=60)
        assert failed is not None and failed["error"] == "HistoryExpiredError", "not told it fell behind"
        ids = [e["id"] for e in probe.watch_events(watch)]
        assert 0 < len(ids) < 3000, "some events were delivered, then the watcher was told it fell behind"
        assert ids == [f"p{i}" for i in range(len(ids))], "no gap before the failure"
        # Resynchronising: a new watch on a new stream gets the changes from now on.
        again = probe.watch(local_type("cast.testing.Pose"))
        py.add("after", Pose(label="after"))
        assert [e["id"] for e in probe.watch_events(again, 1, 10000)] == ["after"]
        assert probe.quit() == 0
    finally:
        py._cast_close()
        probe.close()


# ------------------------------------------------------------------ TLS


def tls_from_the_launch_contract(lang: str, tmp_path: Path, pki: dict[str, Path], component: str) -> None:
    """CAST_TLS_CA makes the component connect over TLS; wrong or incomplete settings exit 2, said in words."""
    handle = serve_tls(tmp_path, pki)
    try:
        env = handle.env(component, "vision")
        env["CAST_TLS_CA"] = str(pki["ca"])
        status, answers, out = run_script(lang, env, [
            {"op": "add", "id": "x", "type": COUNTER, "value": counter_json(component, 7)},
            {"op": "get", "id": "x", "type": COUNTER},
        ])
        assert status == 0, out
        assert answers[1]["value"] == counter_json(component, 7), answers
        # Without the CA (plaintext) or trusting another CA, the component cannot connect: it asks again for
        # its connect window (CAST_CONNECT_WINDOW_S, 1 s here instead of 20), then gives up saying so.
        env["CAST_CONNECT_WINDOW_S"] = "1"
        env.pop("CAST_TLS_CA")
        status, _, out = run_script(lang, env, [])
        assert status == 2 and "unavailable" in out, out
        env["CAST_TLS_CA"] = str(pki["other_ca"])
        status, _, out = run_script(lang, env, [])
        assert status == 2 and "no CAST system answered at" in out and "within 1 s" in out, out
        status, _, out = run_script(lang, {**env, "CAST_CONNECT_WINDOW_S": "soon"}, [])
        assert status == 2 and "CAST_CONNECT_WINDOW_S 'soon': give the seconds" in out, out
        # Incomplete settings are a bad launch environment, said in words.
        env.update(CAST_TLS_CA=str(pki["ca"]), CAST_TLS_CERT=str(pki["client_cert"]))
        status, _, out = run_script(lang, env, [])
        assert status == 2 and "set both CAST_TLS_CERT and CAST_TLS_KEY" in out, out
        env.update(CAST_TLS_CA=str(tmp_path / "missing.pem"))
        env.pop("CAST_TLS_CERT")
        status, _, out = run_script(lang, env, [])
        assert status == 2 and "cannot read a TLS file" in out, out
    finally:
        handle.stop()


def client_certificates_when_required(lang: str, tmp_path: Path, pki: dict[str, Path], component: str) -> None:
    """A server requiring client certificates refuses a component without one and accepts it with one."""
    handle = serve_tls(tmp_path, pki, client_auth=True)
    try:
        env = handle.env(component, "vision")
        env["CAST_TLS_CA"] = str(pki["ca"])
        env["CAST_CONNECT_WINDOW_S"] = "1"  # refused at the handshake: asked again for 1 s, not 20
        status, _, out = run_script(lang, env, [])
        assert status == 2, f"connected without a client certificate\n{out}"
        env.update(CAST_TLS_CERT=str(pki["client_cert"]), CAST_TLS_KEY=str(pki["client_key"]))
        status, answers, out = run_script(lang, env, [
            {"op": "add", "id": "y", "type": COUNTER, "value": counter_json(component, 1)},
        ])
        assert status == 0 and answers[0]["ok"] and "revision" in answers[0], out
    finally:
        handle.stop()


# ------------------------------------------------------------------ renewed tokens


def renewed_token_file_keeps_the_component_working(lang: str, server: ServerHandle, tmp_path: Path,
                                                    prefix: str) -> None:
    """A component whose short-lived token is renewed through CAST_TOKEN_FILE keeps working past its
    expiry; one with a fixed token is refused once it has expired."""
    renewed_id, fixed_id = f"{prefix}renewed", f"{prefix}fixed"
    with renewing_token_file(server.signer, Identity(renewed_id, "vision"), tmp_path / f"{renewed_id}.token") as path:
        env = server.env(renewed_id, "vision")
        env.update(CAST_TOKEN=path.read_text().strip(), CAST_TOKEN_FILE=str(path))
        renewed = start(lang, env)
        fixed_env = server.env(fixed_id, "vision")
        # Long enough for a JVM to start and make its first write on a loaded machine (2 s was not),
        # short enough to run out within the test.
        fixed_ttl = 6.0
        fixed_expiry = time.time() + fixed_ttl
        fixed_env["CAST_TOKEN"] = server.signer.issue(Identity(fixed_id, "vision"), ttl_seconds=fixed_ttl)
        fixed = start(lang, fixed_env)
        try:
            renewed.ready()
            fixed.ready()
            renewed.ok("add", id="r", type=COUNTER, value=counter_json(renewed_id, 0))
            fixed.ok("add", id="f", type=COUNTER, value=counter_json(fixed_id, 0))
            # Well past the first renewed token's expiry and the fixed token's (whole seconds, rounded up).
            deadline = time.monotonic() + max(4.5, fixed_expiry + 1.5 - time.time())
            i = 0
            while time.monotonic() < deadline:
                i += 1
                renewed.ok("overwrite", id="r", type=COUNTER, value=counter_json(renewed_id, i))
                time.sleep(0.1)
            err = fixed.fails(
                "UnauthenticatedError", "overwrite", id="f", type=COUNTER, value=counter_json(fixed_id, 1)
            )
            assert "expired" in err["message"], err
            assert renewed.quit() == 0
        finally:
            renewed.close()
            fixed.close()
