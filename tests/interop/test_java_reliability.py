"""The Java client under failures: server restarts (resume without gap, or the resync signal), a cut
connection, TLS from the launch contract, and tokens renewed through CAST_TOKEN_FILE."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import yaml
from cast_testing_pb2 import Counter

import cast
from cast.core.records import Identity
from cast.v1 import directory_pb2
from tests.conftest import ServerHandle
from tests.interop.java_support import TEST_CLASSES, CastRun, JavaComponent, counter_json
from tests.interop.restart_support import restart_config, write_until
from tests.reliability.conftest import kill9, serve, serve_tls, wait_for
from tests.reliability.proxy import Proxy

VISION = [{"kind": "operation", "sa": "vision"}]


def _revisions(jc: JavaComponent, watch: int, count: int, timeout_ms: int = 20000) -> list[int]:
    stats = jc.ok("watch_stats", watch=watch, expected=count, timeout_ms=timeout_ms, timeout=timeout_ms / 1000 + 10)
    return [int(e["revision"]) for e in stats["events"] if e["sa"] == "vision"]


def _info(handle: ServerHandle, component: str) -> Any:
    import grpc

    from cast.v1 import directory_pb2, directory_pb2_grpc

    with grpc.insecure_channel(handle.endpoint) as channel:
        desc = directory_pb2_grpc.DirectoryStub(channel).DescribeSystem(
            directory_pb2.DescribeSystemRequest(),
            metadata=(("authorization", f"Bearer {handle.token('tool', 'vision')}"),), timeout=5)
    return {c.id: c for c in desc.components}.get(component)


def test_java_watch_resumes_without_gap_or_duplicate_after_a_server_restart(tmp_path: Path) -> None:
    config = restart_config(tmp_path, persistence=True)
    server = serve(config)
    port = server.endpoint.rpartition(":")[2]
    jc = JavaComponent(server.env("jwatcher", "vision"))
    writer = None
    try:
        jc.ready()
        watch = jc.ok("watch", filters=VISION)["watch"]
        writer = server.connect("writer", "vision")
        write_until(writer, "a", 50)
        assert _revisions(jc, watch, 50) == list(range(1, 51))
        kill9(server)
        # While the server is away a call fails promptly with a clear error; it does not hang.
        started = time.monotonic()
        err = jc.fails("get", "UnavailableError", id="a-0", type="cast.testing.Counter")
        assert "unavailable" in err["message"] and "retry" in err["message"], err
        assert time.monotonic() - started < 25
        server = serve(config, listen=f"127.0.0.1:{port}")
        write_until(writer, "b", 50)
        top = writer.get_entry("b-49", Counter).revision
        revs = _revisions(jc, watch, top)
        assert revs == list(range(1, top + 1)), "gap or duplicate"
        jc.no_event("watch_failed", within=0.5)
        # The session was registered again with the restarted server.
        running = directory_pb2.COMPONENT_STATE_RUNNING
        wait_for(lambda: (i := _info(server, "jwatcher")) is not None and i.state == running,
                 timeout=30, what="re-registration")
        assert jc.ok("get", id="b-0", type="cast.testing.Counter")["value"] == {}
        assert jc.quit() == 0
    finally:
        if writer is not None:
            writer._cast_close()
        jc.close()
        server.stop()


def test_a_server_restarted_without_its_history_gives_java_the_resync_signal(tmp_path: Path) -> None:
    config = restart_config(tmp_path, persistence=False)
    server = serve(config)
    port = server.endpoint.rpartition(":")[2]
    jc = JavaComponent(server.env("jwatcher", "vision"))
    writer = None
    try:
        jc.ready()
        watch = jc.ok("watch", filters=VISION)["watch"]
        writer = server.connect("writer", "vision")
        write_until(writer, "a", 5)
        assert _revisions(jc, watch, 5) == [1, 2, 3, 4, 5]
        kill9(server)
        server = serve(config, listen=f"127.0.0.1:{port}")
        # The new server starts at revision 0 again: resuming at 6 would silently mix two histories.
        write_until(writer, "b", 10)
        failed = jc.wait_event("watch_failed", timeout=30)
        assert failed["error"] == "HistoryExpiredError", failed
        assert "resynchronise" in failed["message"], failed
        assert _revisions(jc, watch, 0) == [1, 2, 3, 4, 5], "nothing from the other history"
        assert jc.ok("watch_stats", watch=watch)["active"] is False
        # Resynchronising: read the state, watch again.
        assert len(jc.ok("get_all", type="cast.testing.Counter")["entries"]) == 10
        again = jc.ok("watch", filters=VISION)["watch"]
        writer.add("c", Counter(value=1))
        assert len(_revisions(jc, again, 1)) == 1
        assert jc.quit() == 0
    finally:
        if writer is not None:
            writer._cast_close()
        jc.close()
        server.stop()


def test_a_cut_connection_releases_java_locks_and_the_watch_catches_up(server: ServerHandle) -> None:
    proxy = Proxy(server.endpoint)
    env = server.env("jholder", "vision")
    env["CAST_ENDPOINT"] = proxy.endpoint
    jc = JavaComponent(env)
    other = server.connect("other", "vision")
    try:
        jc.ready()
        jc.ok("add", id="doc", type="cast.testing.Counter", value=counter_json("jholder", 1))
        watch = jc.ok("watch", filters=VISION)["watch"]
        jc.ok("lock", id="doc", mode="OD")
        assert not other.try_lock("doc")
        proxy.cut()
        # The server notices the broken streams, ends the session and releases the lock.
        wait_for(lambda: other.try_lock("doc"), timeout=30, what="the lock to be released")
        other.unlock("doc")
        for i in range(20):
            other.add(f"while-cut-{i}", Counter(value=i))
        proxy.restore()
        top = other.get_entry("while-cut-19", Counter).revision
        revs = _revisions(jc, watch, top - 1)  # every change after the add of "doc" (revision 1)
        assert revs == list(range(2, top + 1)), "the watcher caught up with no gap and no duplicate"
        wait_for(lambda: _info(server, "jholder").sessions >= 2, timeout=30, what="re-registration")
        # Locks do not survive a disconnect: the holder takes it again.
        assert jc.ok("lock", id="doc", mode="OD", timeout_ms=10000)["depth"] == 1
        assert not other.try_lock("doc")
        assert jc.quit() == 0
    finally:
        other._cast_close()
        jc.close()
        proxy.close()


# ------------------------------------------------------------------ TLS


def _run(env: dict[str, str], commands: list[dict[str, Any]]) -> tuple[int, list[dict[str, Any]], str]:
    """Start Driven, run commands, quit; (exit status, answers, output)."""
    jc = JavaComponent(env)
    try:
        answers = []
        if commands:
            try:
                jc.ready(30)
            except AssertionError:
                return jc.wait(30), [], jc.output()
            answers = [jc.call(c.pop("op"), **c) for c in commands]
        status = jc.quit(30) if commands else jc.wait(60)
        time.sleep(0.1)
        return status, answers, jc.output()
    finally:
        jc.close()


def test_java_component_uses_tls_from_the_launch_contract(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki)
    try:
        env = handle.env("jtls", "vision")
        env["CAST_TLS_CA"] = str(pki["ca"])
        status, answers, out = _run(env, [
            {"op": "add", "id": "x", "type": "cast.testing.Counter", "value": counter_json("jtls", 7)},
            {"op": "get", "id": "x", "type": "cast.testing.Counter"},
        ])
        assert status == 0, out
        assert answers[1]["value"] == {"writer": "jtls", "value": "7"}, answers
        # Without the CA (plaintext) or trusting another CA, the component cannot connect.
        env.pop("CAST_TLS_CA")
        status, _, out = _run(env, [])
        assert status == 2 and "unavailable" in out, out
        env["CAST_TLS_CA"] = str(pki["other_ca"])
        status, _, out = _run(env, [])
        assert status == 2 and "cannot join the system" in out, out
        # Incomplete settings are a bad launch environment, said in words.
        env.update(CAST_TLS_CA=str(pki["ca"]), CAST_TLS_CERT=str(pki["client_cert"]))
        status, _, out = _run(env, [])
        assert status == 2 and "set both CAST_TLS_CERT and CAST_TLS_KEY" in out, out
        env.update(CAST_TLS_CA=str(tmp_path / "missing.pem"))
        env.pop("CAST_TLS_CERT")
        status, _, out = _run(env, [])
        assert status == 2 and "cannot read a TLS file" in out, out
    finally:
        handle.stop()


def test_java_client_certificates_when_the_server_requires_them(tmp_path: Path, pki: dict[str, Path]) -> None:
    handle = serve_tls(tmp_path, pki, client_auth=True)
    try:
        env = handle.env("jmtls", "vision")
        env["CAST_TLS_CA"] = str(pki["ca"])
        status, _, out = _run(env, [])
        assert status == 2, f"connected without a client certificate\n{out}"
        env.update(CAST_TLS_CERT=str(pki["client_cert"]), CAST_TLS_KEY=str(pki["client_key"]))
        status, answers, out = _run(env, [
            {"op": "add", "id": "y", "type": "cast.testing.Counter", "value": counter_json("jmtls", 1)},
        ])
        assert status == 0 and answers[0]["ok"], out
    finally:
        handle.stop()


# ------------------------------------------------------------------ renewed tokens


def test_an_expiring_token_renewed_through_its_file_keeps_the_java_component_working(
    server: ServerHandle, tmp_path: Path
) -> None:
    identity = Identity("jrenewed", "vision")
    path = tmp_path / "jrenewed.token"
    path.write_text(server.signer.issue(identity, ttl_seconds=2))
    stop = threading.Event()

    def renewer() -> None:  # what the orchestrator does (cast.orchestrator.security)
        while not stop.wait(0.5):
            tmp = path.with_suffix(".tmp")
            tmp.write_text(server.signer.issue(identity, ttl_seconds=2))
            tmp.replace(path)

    threading.Thread(target=renewer, daemon=True).start()
    env = server.env("jrenewed", "vision")
    env.update(CAST_TOKEN=path.read_text().strip(), CAST_TOKEN_FILE=str(path))
    renewed = JavaComponent(env)
    fixed_env = server.env("jfixed", "vision")
    fixed_env["CAST_TOKEN"] = server.signer.issue(Identity("jfixed", "vision"), ttl_seconds=2)
    fixed = JavaComponent(fixed_env)
    try:
        renewed.ready()
        fixed.ready()
        renewed.ok("add", id="r", type="cast.testing.Counter", value=counter_json("jrenewed", 0))
        fixed.ok("add", id="f", type="cast.testing.Counter", value=counter_json("jfixed", 0))
        deadline = time.monotonic() + 4.5  # well past the first tokens' expiry
        i = 0
        while time.monotonic() < deadline:
            i += 1
            renewed.ok("overwrite", id="r", type="cast.testing.Counter", value=counter_json("jrenewed", i))
            time.sleep(0.1)
        err = fixed.fails("overwrite", "UnauthenticatedError", id="f", type="cast.testing.Counter",
                          value=counter_json("jfixed", 1))
        assert "expired" in err["message"], err
        assert renewed.quit() == 0
    finally:
        stop.set()
        renewed.close()
        fixed.close()


def test_the_orchestrator_renews_tokens_of_java_components(tmp_path: Path) -> None:
    """Under `cast run` with auth.token_ttl, a Java component gets CAST_TOKEN_FILE and keeps working."""
    config = tmp_path / "system.yaml"
    config.write_text(yaml.safe_dump({
        "system": "ttl",
        "auth": {"token_ttl": 2},
        "subarchitectures": {"vision": {"components": {"echo": {
            "language": "java", "kind": "managed", "class": "cast.itest.Echo", "classpath": [str(TEST_CLASSES)],
        }}}},
    }, sort_keys=False))
    run = CastRun(config, tmp_path / "runtime", tmp_path)
    py = None
    try:
        run.wait_running("echo")
        py = run.connect("pywriter", "vision")
        time.sleep(3.5)  # the token the Java component started with has expired by now
        answered = threading.Event()
        py.on_change(cast.address_filter("echo-late"), lambda change: answered.set())
        py.add("late", Counter(value=41))
        assert answered.wait(20), run.output()
        assert py.get("echo-late", Counter) == Counter(writer="echo", value=42)
    finally:
        if py is not None:
            py._cast_close()
        run.stop()
