"""The C++ client under failures: server restarts (resume without gap, or the resync signal), a cut
connection, TLS from the launch contract, and tokens renewed through CAST_TOKEN_FILE."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter

from cast.core.records import Identity
from tests.conftest import ServerHandle
from tests.interop.cpp_support import CastRun, CppProbe
from tests.interop.restart_support import restart_config, write_until
from tests.reliability.conftest import kill9, serve, serve_tls, wait_for, write_config
from tests.reliability.proxy import Proxy

COUNTER = "cast.testing.Counter"
ALL_VISION = {"filters": [{"kind": "operation", "ops": [], "sa": "local"}]}


def _revisions(probe: CppProbe, count: int, timeout_ms: int = 20000) -> tuple[list[int], str]:
    got = probe.ok("events", "all", count, timeout_ms, timeout=timeout_ms / 1000 + 10)
    return [e["revision"] for e in got["events"]], got["error"]


def _session(handle: ServerHandle, component: str) -> tuple[int, str]:
    """(sessions, live session id) of a component as the server knows it; (0, "") if unknown."""
    import grpc

    from cast.v1 import directory_pb2, directory_pb2_grpc

    with grpc.insecure_channel(handle.endpoint) as channel:
        desc = directory_pb2_grpc.DirectoryStub(channel).DescribeSystem(
            directory_pb2.DescribeSystemRequest(),
            metadata=(("authorization", f"Bearer {handle.token('tool', 'vision')}"),), timeout=5)
    return next(((c.sessions, c.session_id) for c in desc.components if c.id == component), (0, ""))


def test_cpp_watch_resumes_without_gap_or_duplicate_after_a_server_restart(tmp_path: Path) -> None:
    config = restart_config(tmp_path, persistence=True)
    server = serve(config)
    port = server.endpoint.rpartition(":")[2]
    probe = CppProbe(server.env("cwatcher", "vision"))
    writer = None
    try:
        probe.ready()
        probe.ok("watch", "all", ALL_VISION)
        writer = server.connect("writer", "vision")
        write_until(writer, "a", 50)
        assert _revisions(probe, 50)[0] == list(range(1, 51))
        kill9(server)
        # While the server is away a C++ call fails promptly with a clear error; it does not hang.
        started = time.monotonic()
        err = probe.fails("UnavailableError", "get", COUNTER, "a-0", "-", timeout=40)
        assert "unavailable" in err["message"] and time.monotonic() - started < 35, err
        server = serve(config, listen=f"127.0.0.1:{port}")
        write_until(writer, "b", 50)
        top = writer.get_entry("b-49", Counter).revision
        revs, error = _revisions(probe, top, 30000)
        assert revs == list(range(1, top + 1)), "gap or duplicate"
        assert error == ""
        # The C++ component registered with the new server process (which knew nothing of
        # its old session), and writes again.
        wait_for(lambda: _session(server, "cwatcher")[1] != "", what="re-registration")
        probe.ok("add", COUNTER, "after", "-", {"writer": "cwatcher", "value": "1"})
        assert probe.quit() == 0
    finally:
        if writer is not None:
            writer._cast_close()
        probe.close()
        server.stop()


def test_a_server_restarted_without_its_history_gives_cpp_the_resync_signal(tmp_path: Path) -> None:
    config = restart_config(tmp_path, persistence=False)
    server = serve(config)
    port = server.endpoint.rpartition(":")[2]
    probe = CppProbe(server.env("cwatcher", "vision"))
    writer = None
    try:
        probe.ready()
        probe.ok("watch", "all", ALL_VISION)
        writer = server.connect("writer", "vision")
        write_until(writer, "a", 5)
        assert _revisions(probe, 5)[0] == [1, 2, 3, 4, 5]
        kill9(server)
        server = serve(config, listen=f"127.0.0.1:{port}")
        # The new server starts at revision 0 again: resuming at 6 would silently mix two histories.
        write_until(writer, "b", 10)
        deadline = time.monotonic() + 30
        while _revisions(probe, 0, 0)[1] == "" and time.monotonic() < deadline:
            time.sleep(0.1)
        revs, error = _revisions(probe, 0, 0)
        assert error == "HistoryExpiredError", "watchFailed was not told to resynchronise"
        assert revs == [1, 2, 3, 4, 5], "nothing from the other history"
        # Resynchronising works: a new watch on the new history.
        probe.ok("watch", "again", ALL_VISION)
        writer.add("c", Counter(value=1))
        assert len(probe.ok("events", "again", 1, 10000)["events"]) == 1
        assert probe.quit() == 0
    finally:
        if writer is not None:
            writer._cast_close()
        probe.close()
        server.stop()


def test_a_cut_connection_releases_cpp_locks_and_the_watch_catches_up(server: ServerHandle) -> None:
    proxy = Proxy(server.endpoint)
    via_proxy = ServerHandle(server.process, proxy.endpoint, server.config_path)
    probe = CppProbe(via_proxy.env("choldr", "vision"))
    other = server.connect("other", "vision")
    try:
        probe.ready()
        probe.ok("add", COUNTER, "doc", "-", {"writer": "choldr", "value": "1"})
        probe.ok("watch", "all", ALL_VISION)
        probe.ok("lock", "doc", "OD", "-", "-")
        assert not other.try_lock("doc")
        proxy.cut()
        # The server notices the broken streams, ends the session and releases the lock.
        wait_for(lambda: other.try_lock("doc"), what="the lock to be released")
        other.unlock("doc")
        for i in range(20):
            other.add(f"while-cut-{i}", Counter(value=i))
        proxy.restore()
        top = other.get_entry("while-cut-19", Counter).revision
        revs, error = _revisions(probe, top - 1, 30000)  # everything after the probe's own add
        assert revs == list(range(2, top + 1)) and error == ""
        wait_for(lambda: _session(server, "choldr")[0] >= 2, what="re-registration")
        # Locks do not survive a disconnect: the holder must take it again.
        assert probe.ok("lock", "doc", "OD", "-", 5000) == {"depth": 1}
        assert not other.try_lock("doc")
        assert probe.quit() == 0
    finally:
        other._cast_close()
        probe.close()
        proxy.close()


# ------------------------------------------------------------------ TLS


def _run_probe(env: dict[str, str], commands: list[str]) -> tuple[int, str]:
    probe = CppProbe(env)
    try:
        assert probe.proc.stdin is not None
        try:
            probe.proc.stdin.write("".join(c + "\n" for c in commands))
            probe.proc.stdin.close()  # EOF: the probe stops after the commands
        except BrokenPipeError:
            pass  # the probe already exited (it could not connect): its status and output say why
        status = probe.wait(60)
        time.sleep(0.1)
        return status, probe.output()
    finally:
        probe.close()


def test_cpp_component_uses_tls_from_the_launch_contract(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki)
    try:
        env = handle.env("ctls", "vision")
        env["CAST_TLS_CA"] = str(pki["ca"])
        status, out = _run_probe(env, ['add Counter x - {"writer": "ctls", "value": "7"}', "get Counter x -"])
        assert status == 0, out
        assert '"value": {"writer":"ctls","value":"7"}' in out, out
        # Without the CA (plaintext) or trusting another CA, the component cannot connect.
        env.pop("CAST_TLS_CA")
        status, out = _run_probe(env, ["ping"])
        assert status == 2 and "unavailable" in out, out
        env["CAST_TLS_CA"] = str(pki["other_ca"])
        status, out = _run_probe(env, ["ping"])
        assert status == 2, out
        # Incomplete settings are a bad launch environment, said in words.
        env.update(CAST_TLS_CA=str(pki["ca"]), CAST_TLS_CERT=str(pki["client_cert"]))
        status, out = _run_probe(env, ["ping"])
        assert status == 2 and "set both CAST_TLS_CERT and CAST_TLS_KEY" in out, out
        env.update(CAST_TLS_CA=str(tmp_path / "missing.pem"))
        env.pop("CAST_TLS_CERT")
        status, out = _run_probe(env, ["ping"])
        assert status == 2 and "cannot read a TLS file" in out, out
    finally:
        handle.stop()


def test_cpp_client_certificates_when_the_server_requires_them(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki, client_auth=True)
    try:
        env = handle.env("cmtls", "vision")
        env["CAST_TLS_CA"] = str(pki["ca"])
        status, out = _run_probe(env, ["ping"])
        assert status == 2, f"connected without a client certificate\n{out}"
        env.update(CAST_TLS_CERT=str(pki["client_cert"]), CAST_TLS_KEY=str(pki["client_key"]))
        status, out = _run_probe(env, ['add Counter y - {"writer": "cmtls", "value": "1"}'])
        assert status == 0 and '"ok": true, "result": {"revision"' in out, out
    finally:
        handle.stop()


# ------------------------------------------------------------------ renewed tokens


def test_an_expiring_token_renewed_through_its_file_keeps_the_cpp_component_working(
    server: ServerHandle, tmp_path: Path
) -> None:
    identity = Identity("crenewed", "vision")
    path = tmp_path / "crenewed.token"
    path.write_text(server.signer.issue(identity, ttl_seconds=2))
    stop = threading.Event()

    def renewer() -> None:  # what the orchestrator does (cast.orchestrator.security)
        while not stop.wait(0.5):
            tmp = path.with_suffix(".tmp")
            tmp.write_text(server.signer.issue(identity, ttl_seconds=2))
            tmp.replace(path)

    threading.Thread(target=renewer, daemon=True).start()
    env = server.env("crenewed", "vision")
    env.update(CAST_TOKEN=path.read_text().strip(), CAST_TOKEN_FILE=str(path))
    renewed = CppProbe(env)
    fixed_env = server.env("cfixed", "vision")
    fixed_env["CAST_TOKEN"] = server.signer.issue(Identity("cfixed", "vision"), ttl_seconds=2)
    fixed = CppProbe(fixed_env)
    try:
        renewed.ready()
        fixed.ready()
        renewed.ok("add", COUNTER, "r", "-", {"value": "0"})
        fixed.ok("add", COUNTER, "f", "-", {"value": "0"})
        deadline = time.monotonic() + 4.5  # well past the first tokens' expiry
        i = 0
        while time.monotonic() < deadline:
            i += 1
            renewed.ok("overwrite", COUNTER, "r", "-", "-", {"value": str(i)})
            time.sleep(0.1)
        err = fixed.fails("UnauthenticatedError", "overwrite", COUNTER, "f", "-", "-", {"value": "1"})
        assert "expired" in err["message"], err
        assert renewed.quit() == 0
    finally:
        stop.set()
        renewed.close()
        fixed.close()


def test_the_orchestrator_renews_tokens_of_cpp_components(tmp_path: Path) -> None:
    """Under `cast run` with auth.token_ttl, a C++ component gets CAST_TOKEN_FILE and keeps working."""
    config = write_config(tmp_path / "system.yaml", {
        "system": "ttl",
        "auth": {"token_ttl": 2},
        "subarchitectures": {"vision": {"components": {"worker": {
            "language": "cpp", "kind": "managed", "run": "cast_test_tasker",
            "args": {"tasks": 3, "work_ms": 4000},
        }}}},
    })
    run = CastRun(config, tmp_path / "runtime")
    try:
        run.state()
        # The tasks are adopted at once (policy always) and completed 4 s later, when the
        # token the component started with has expired: only a renewed token gets them through.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and sum('"completed"' in line for line in run.lines) < 3:
            time.sleep(0.1)
        assert sum('"completed"' in line for line in run.lines) == 3, run.output()
        assert not any("complete_failed" in line for line in run.lines), run.output()
    finally:
        run.stop()


def test_a_stuck_cpp_watcher_never_blocks_writers_and_is_told_past_the_history(server_factory: Any) -> None:
    from cast_testing_pb2 import Pose

    server = server_factory({"system": "lag", "limits": {"history_events": 64}, "subarchitectures": {"vision": {}}})
    env = dict(server.env("cslow", "vision"), CAST_PROBE_MAX_PENDING="4")
    probe = CppProbe(env)
    py = server.connect("pyfast", "vision")
    try:
        probe.ready()
        probe.ok("watch", "stuck", {"gated": True, "filters": [
            {"kind": "local", "type": "cast.testing.Pose", "include_entry": True}]})
        # Far more than the history, in events and in bytes (past the transport's buffers), while
        # the C++ callback is stuck: the writer is never held up.
        label = "x" * 2048
        started = time.monotonic()
        for i in range(3000):
            py.add(f"p{i}", Pose(x=i, label=label))
        assert time.monotonic() - started < 60
        probe.ok("open_gate")
        deadline = time.monotonic() + 60
        while (got := probe.ok("events", "stuck", 0, 0))["error"] == "" and time.monotonic() < deadline:
            time.sleep(0.1)
        assert got["error"] == "HistoryExpiredError", "the watcher was not told it fell behind"
        ids = [e["id"] for e in got["events"]]
        assert 0 < len(ids) < 3000, "some events were delivered, then the watcher was told it fell behind"
        assert ids == [f"p{i}" for i in range(len(ids))], "no gap before the failure"
        # Resynchronising: a new watch on a new stream gets the changes from now on.
        probe.ok("watch", "again", {"filters": [{"kind": "local", "type": "cast.testing.Pose"}]})
        py.add("after", Pose(label="after"))
        assert [e["id"] for e in probe.ok("events", "again", 1, 10000)["events"]] == ["after"]
        assert probe.quit() == 0
    finally:
        py._cast_close()
        probe.close()
