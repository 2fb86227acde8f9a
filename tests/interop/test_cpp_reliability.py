"""The C++ client under failures: server restarts (resume without gap, or the resync signal), a cut
connection, a stuck watcher, TLS from the launch contract, and tokens renewed through CAST_TOKEN_FILE.

The scenarios are shared with Java (tests/interop/scenarios_reliability.py); only the orchestrator's
token renewal, which runs a different component per language, is written here."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from tests.conftest import ServerHandle
from tests.interop import scenarios_reliability as s
from tests.interop.cpp_support import cast_run
from tests.reliability.conftest import write_config


def test_cpp_watch_resumes_without_gap_or_duplicate_after_a_server_restart(tmp_path: Path) -> None:
    s.watch_resumes_after_a_server_restart("cpp", tmp_path, "cwatcher")


def test_a_server_restarted_without_its_history_gives_cpp_the_resync_signal(tmp_path: Path) -> None:
    s.restart_without_history_gives_the_resync_signal("cpp", tmp_path, "cwatcher")


def test_a_cut_connection_releases_cpp_locks_and_the_watch_catches_up(server: ServerHandle) -> None:
    s.cut_connection_releases_locks_and_the_watch_catches_up("cpp", server, "choldr")


def test_a_stuck_cpp_watcher_never_blocks_writers_and_is_told_past_the_history(server_factory: Any) -> None:
    s.stuck_watcher_never_blocks_writers("cpp", server_factory, "cslow")


# ------------------------------------------------------------------ TLS


def test_cpp_component_uses_tls_from_the_launch_contract(tmp_path: Path, pki: dict[str, Path]) -> None:
    s.tls_from_the_launch_contract("cpp", tmp_path, pki, "ctls")


def test_cpp_client_certificates_when_the_server_requires_them(tmp_path: Path, pki: dict[str, Path]) -> None:
    s.client_certificates_when_required("cpp", tmp_path, pki, "cmtls")


# ------------------------------------------------------------------ renewed tokens


def test_an_expiring_token_renewed_through_its_file_keeps_the_cpp_component_working(
    server: ServerHandle, tmp_path: Path
) -> None:
    s.renewed_token_file_keeps_the_component_working("cpp", server, tmp_path, "c")


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
    run = cast_run(config, tmp_path / "runtime")
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
