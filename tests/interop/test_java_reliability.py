"""The Java client under failures: server restarts (resume without gap, or the resync signal), a cut
connection, a stuck watcher, TLS from the launch contract, and tokens renewed through CAST_TOKEN_FILE.

The scenarios are shared with C++ (tests/interop/scenarios_reliability.py); only the orchestrator's
token renewal, which runs a different component per language, is written here."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import yaml
from cast_testing_pb2 import Counter

import cast
from tests.conftest import ServerHandle
from tests.interop import scenarios_reliability as s
from tests.interop.java_support import TEST_CLASSES, cast_run


def test_java_watch_resumes_without_gap_or_duplicate_after_a_server_restart(tmp_path: Path) -> None:
    s.watch_resumes_after_a_server_restart("java", tmp_path, "jwatcher")


def test_a_server_restarted_without_its_history_gives_java_the_resync_signal(tmp_path: Path) -> None:
    s.restart_without_history_gives_the_resync_signal("java", tmp_path, "jwatcher")


def test_a_cut_connection_releases_java_locks_and_the_watch_catches_up(server: ServerHandle) -> None:
    s.cut_connection_releases_locks_and_the_watch_catches_up("java", server, "jholder")


def test_a_stuck_java_watcher_never_blocks_writers_and_is_told_past_the_history(server_factory: Any) -> None:
    s.stuck_watcher_never_blocks_writers("java", server_factory, "jslow")


# ------------------------------------------------------------------ TLS


def test_java_component_uses_tls_from_the_launch_contract(tmp_path: Path, pki: dict[str, Path]) -> None:
    s.tls_from_the_launch_contract("java", tmp_path, pki, "jtls")


def test_java_client_certificates_when_the_server_requires_them(tmp_path: Path, pki: dict[str, Path]) -> None:
    s.client_certificates_when_required("java", tmp_path, pki, "jmtls")


# ------------------------------------------------------------------ renewed tokens


def test_an_expiring_token_renewed_through_its_file_keeps_the_java_component_working(
    server: ServerHandle, tmp_path: Path
) -> None:
    s.renewed_token_file_keeps_the_component_working("java", server, tmp_path, "j")


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
    run = cast_run(config, tmp_path / "runtime", tmp_path)
    py = None
    try:
        run.wait_for_component("echo", "running", 30)
        py = run.act_as("pywriter", "vision")
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
