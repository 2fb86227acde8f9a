"""``cast.connect`` from a plain script: launch environment, runtime directory of `cast run`, explicit token."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from google.protobuf.wrappers_pb2 import StringValue

import cast
from tests.conftest import PYTHONPATH, SECRET, ServerHandle

SCRIPT = textwrap.dedent("""
    import json, sys, threading
    from google.protobuf.wrappers_pb2 import StringValue
    import cast

    seen = threading.Event()
    with cast.connect() as wm:
        wm.on_change(cast.address_filter("from-script"), lambda change: seen.set())
        result = wm.add("from-script", StringValue(value="hi"))
        with wm.lock("from-script"):
            wm.overwrite("from-script", StringValue(value="hi again"), expected_version=result.version)
        assert seen.wait(10)
        print(json.dumps({"id": wm.component_id, "sa": wm.subarchitecture}))
""")


def _run_script(env: dict[str, str], cwd: Path) -> dict[str, str]:
    full = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    full.update(env, PYTHONPATH=PYTHONPATH)
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=full, cwd=cwd, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def test_a_script_connects_from_the_launch_environment(server: ServerHandle, tmp_path: Path) -> None:
    out = _run_script(server.env("notebook", "language"), tmp_path)
    assert out == {"id": "notebook", "sa": "language"}
    reader = server.connect("reader", "vision")
    assert reader.get("from-script", StringValue, subarchitecture="language").value == "hi again"
    reader._cast_close()


def test_a_script_connects_through_the_runtime_directory_of_cast_run(server: ServerHandle, tmp_path: Path) -> None:
    runtime = tmp_path / "rt"
    runtime.mkdir()
    (runtime / "system.json").write_text(json.dumps({
        "system": "test", "endpoint": server.endpoint, "pid": os.getpid(),
        "servers": {"main": {"endpoint": server.endpoint, "subarchitectures": ["motor", "vision"]}}, "tls": None,
    }))
    (runtime / "secret").write_text(SECRET + "\n")
    out = _run_script({"CAST_RUNTIME_DIR": str(runtime)}, tmp_path)
    assert out["sa"] == "motor" and out["id"].startswith("script-")
    # Made from the secret, the script's token is privileged: it may write any SA.
    with cast.connect(runtime_dir=runtime, env={}, component_id="nb", subarchitecture="vision") as wm:
        assert (wm.component_id, wm.subarchitecture) == ("nb", "vision")
        wm.add("x", StringValue(value="v"), subarchitecture="language")
        assert wm.get("from-script", StringValue, subarchitecture="motor").value == "hi again"


def test_connect_with_an_explicit_token_and_what_it_says_when_nothing_is_found(
    server: ServerHandle, tmp_path: Path
) -> None:
    with cast.connect(server.endpoint, server.token("explicit", "vision"), env={}) as wm:
        assert wm.component_id == "explicit"
        with pytest.raises(cast.PermissionDeniedError):  # not privileged: its own SA only
            wm.add("y", StringValue(), subarchitecture="language")
    with pytest.raises(cast.InvalidArgumentError, match="token is for component .explicit. .* told component .other."):
        cast.connect(server.endpoint, server.token("explicit", "vision"), component_id="other", env={})
    with pytest.raises(cast.NotFoundError, match="no running system found"):
        cast.connect(env={}, runtime_dir=tmp_path / "none")
    # A CAST_TOKEN_FILE that is set is the token: empty, it is named, not passed over (as by the runners).
    (tmp_path / "empty.token").write_text("\n")
    with pytest.raises(cast.InvalidArgumentError, match="CAST_TOKEN_FILE names .*empty.token, which is empty: point"):
        cast.connect(env={"CAST_ENDPOINT": server.endpoint, "CAST_TOKEN_FILE": str(tmp_path / "empty.token"),
                          "CAST_TOKEN": server.token("explicit", "vision")})


def test_every_variable_connect_reads_comes_from_env_when_it_is_given(
    server: ServerHandle, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The process's own environment names nothing, or something wrong: only `env` counts.
    for name in ("CAST_ENDPOINT", "CAST_TOKEN", "CAST_TOKEN_FILE", "CAST_SECRET"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("CAST_SECRET_FILE", str(tmp_path / "missing-secret"))
    monkeypatch.chdir(tmp_path)  # no .cast/secret here either
    secret_file = tmp_path / "secret"
    secret_file.write_text(SECRET + "\n")
    env = {"CAST_ENDPOINT": server.endpoint, "CAST_SECRET_FILE": str(secret_file),
           "CAST_RUNTIME_DIR": str(tmp_path / "runtime")}
    with cast.connect(env=env, component_id="from-env", subarchitecture="vision") as wm:
        wm.add("from-env", StringValue(value="ok"))
        assert wm.component_id == "from-env"
    with pytest.raises(cast.NotFoundError, match="no token secret"):
        cast.connect(env={**env, "CAST_SECRET_FILE": ""}, component_id="no-secret", subarchitecture="vision")
