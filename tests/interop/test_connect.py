"""Plain programs without a component and stored values that do not parse,
for the C++ and the Java library, against a real `cast serve`.

The programs are cast_test_connect (cpp_client/tests/components) and cast.itest.ConnectScript
(java_client/src/test/java): each connects with its library's connect() and nothing else, watches
an entry, adds it, reads it back, waits for the change and prints one JSON line.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Counter
from google.protobuf import any_pb2

from cast.v1 import entry_pb2, working_memory_pb2, working_memory_pb2_grpc
from tests.conftest import SECRET
from tests.interop.cpp_support import cpp_executable
from tests.interop.java_support import java_classpath
from tests.interop.probes import COUNTER, start

LANGS = ["cpp", "java"]


def script_command(lang: str) -> list[str]:
    """How to start the test program of ``lang``."""
    if lang == "cpp":
        return [str(cpp_executable("cast_test_connect"))]
    return ["java", "-cp", java_classpath(), "cast.itest.ConnectScript"]


def no_cast_env(**extra: str) -> dict[str, str]:
    """This process's environment without any CAST_* variable (so only what a test gives is found)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    env.update(extra)
    return env


def run_script(lang: str, entry_id: str, env: dict[str, str], cwd: Path) -> tuple[int, dict[str, Any]]:
    """Run the program; its exit status and the JSON line it printed."""
    proc = subprocess.run([*script_command(lang), entry_id], env=env, cwd=cwd, capture_output=True, text=True,
                          timeout=120)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    assert lines, f"no JSON line (exit {proc.returncode})\n{proc.stdout}\n--- stderr ---\n{proc.stderr}"
    return proc.returncode, json.loads(lines[-1])


def check_entry(server: Any, entry_id: str, sa: str, writer: str) -> None:
    """The entry the program added is in the WM, as Python reads it."""
    py = server.connect("checker", sa)
    try:
        entry = py.get_entry(entry_id, Counter)
        assert entry.value == Counter(writer=writer, value=42)
        assert entry.author == writer
    finally:
        py._cast_close()


@pytest.mark.parametrize("lang", LANGS)
def test_a_script_connects_from_the_launch_environment(server: Any, lang: str, tmp_path: Path) -> None:
    env = no_cast_env(CAST_ENDPOINT=server.endpoint, CAST_TOKEN=server.token("notebook", "language"))
    status, out = run_script(lang, f"env-{lang}", env, tmp_path)
    assert status == 0, out
    assert out["component"] == "notebook" and out["subarchitecture"] == "language", out
    assert out["privileged"] is False and out["event"] == "ADD" and out["writer"] == "notebook", out
    check_entry(server, f"env-{lang}", "language", "notebook")


@pytest.mark.parametrize("lang", LANGS)
def test_a_script_connects_from_a_runtime_directory(server: Any, lang: str, tmp_path: Path) -> None:
    # What a running `cast run` leaves in its runtime directory (this process stands in for it),
    # found here as the default, .cast in the working directory.
    runtime = tmp_path / ".cast"
    runtime.mkdir()
    (runtime / "system.json").write_text(json.dumps({
        "system": "test",
        "endpoint": server.endpoint,
        "servers": {"main": {"endpoint": server.endpoint, "subarchitectures": ["motor", "vision", "language"]}},
        "pid": os.getpid(),
        "config": str(server.config_path),
        "tls": None,
    }))
    (runtime / "secret").write_text(SECRET + "\n")
    status, out = run_script(lang, f"dir-{lang}", no_cast_env(), tmp_path)
    assert status == 0, out
    # A token minted from the secret: script-<host>-<pid>, the first SA of the first server, privileged.
    assert re.fullmatch(r"script-.+-\d+", out["component"]), out
    assert out["subarchitecture"] == "motor" and out["privileged"] is True and out["event"] == "ADD", out
    check_entry(server, f"dir-{lang}", "motor", out["component"])


@pytest.mark.parametrize("lang", LANGS)
def test_a_script_without_a_system_is_told_what_to_give(lang: str, tmp_path: Path) -> None:
    status, out = run_script(lang, "x", no_cast_env(), tmp_path)
    assert status == 1
    assert out["error"] == "NotFoundError", out
    assert out["message"].startswith("no CAST system to connect to: there is no .cast/system.json"), out
    assert "CAST_ENDPOINT" in out["message"] and "`cast run CONFIG`" in out["message"], out


def store_corrupt_counter(server: Any, entry_id: str) -> None:
    """Store bytes that are no cast.testing.Counter under that type, in vision.

    The server checks a value against its type's schema only once the schema is registered, and
    nothing registered Counter on this fresh server, so the bytes are stored as they are. (A server
    that checks every value refuses them; such a test needs one started with the check off.)
    """
    value = any_pb2.Any(type_url=f"type.googleapis.com/{COUNTER}", value=b"\x0a\x05ab")
    with grpc.insecure_channel(server.endpoint) as channel:
        stub = working_memory_pb2_grpc.WorkingMemoryStub(channel)
        stub.Add(working_memory_pb2.AddRequest(address=entry_pb2.EntryAddress(id=entry_id, subarchitecture="vision"),
                                               value=value),
                 metadata=(("authorization", f"Bearer {server.token('corrupter', 'vision')}"),), timeout=10)


@pytest.mark.parametrize("lang", LANGS)
def test_a_stored_value_that_does_not_parse_is_an_invalid_argument_error(server: Any, lang: str) -> None:
    store_corrupt_counter(server, "bad")
    probe = start(lang, server.env("reader", "vision"))
    try:
        probe.ready()
        err = probe.fails("InvalidArgumentError", "get", id="bad", type=COUNTER)
        message = err["message"]
        assert message.startswith(f"entry 'bad' in subarchitecture 'vision' does not parse as {COUNTER} ("), err
        assert message.endswith("): it was written corrupt or with another schema; overwrite or delete it"), err
        assert probe.quit() == 0
    finally:
        probe.close()
