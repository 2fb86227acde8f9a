"""Who a Java component is comes from the server: RegisterResponse carries the identity
the server verified from the token, and a launch environment or connect options that say otherwise are
refused at start, naming both, against a real `cast serve`. The same rules on an in-memory transport:
java_client/src/test/java/cast/client/IdentityTest.java."""

from __future__ import annotations

import json
import os
import subprocess
from typing import Any

import pytest

from tests.interop.java_support import RUNNER, JavaComponent, java_classpath


def run_java(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["java", "-cp", java_classpath(), *args], env=env, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.parametrize(
    ("launched_as", "token_for", "named"),
    [
        (("jalice", "vision"), ("jbob", "vision"), "CAST_COMPONENT_ID is 'jalice' but the server verified the token "
         "as component 'jbob' of subarchitecture 'vision'"),
        (("jcarol", "vision"), ("jcarol", "motor"), "CAST_SUBARCHITECTURE is 'vision' but the server verified the "
         "token as component 'jcarol' of subarchitecture 'motor'"),
    ],
    ids=["another-id", "another-subarchitecture"],
)
def test_a_component_started_with_a_token_for_another_identity_exits_2_naming_both(
    server: Any, launched_as: tuple[str, str], token_for: tuple[str, str], named: str
) -> None:
    env = dict(server.env(*launched_as), CAST_TOKEN=server.token(*token_for))
    r = run_java(env, RUNNER, "cast.itest.Driven")
    assert r.returncode == 2, r.stderr
    assert named in r.stderr, r.stderr
    assert f"`cast token {launched_as[0]} --sa {launched_as[1]}`" in r.stderr, r.stderr  # what to do
    assert '"event": "ready"' not in r.stdout and '"event":"ready"' not in r.stdout, "no hook ran"


def test_the_component_is_whom_the_server_verified(server: Any) -> None:
    jc = JavaComponent(server.env("jdave", "motor", privileged=True))
    try:
        ready = jc.ready()
        assert (ready["component"], ready["subarchitecture"], ready["privileged"]) == ("jdave", "motor", True)
        assert jc.quit() == 0
    finally:
        jc.close()


def connect_script(env: dict[str, str]) -> tuple[int, dict[str, Any]]:
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("CAST_")}, **env}
    r = run_java(env, "cast.itest.ConnectScript", "identity-probe")
    lines = [line for line in r.stdout.splitlines() if line.startswith("{")]
    assert lines, f"no JSON line (exit {r.returncode})\n{r.stdout}\n{r.stderr}"
    return r.returncode, json.loads(lines[-1])


def test_connect_options_that_contradict_the_token_are_refused_naming_both(server: Any) -> None:
    token = server.token("planner", "vision")
    status, out = connect_script({"CAST_ENDPOINT": server.endpoint, "CAST_TOKEN": token,
                                  "CONNECT_OPTION_COMPONENT_ID": "notebook"})
    assert status == 1 and out["error"] == "InvalidArgumentError", out
    assert out["message"].startswith(
        "ConnectOptions.componentId is 'notebook' but the server verified the token as component 'planner' of "
        "subarchitecture 'vision': the token from CAST_TOKEN decides the identity"), out
    # Options that agree with the token are fine.
    status, out = connect_script({"CAST_ENDPOINT": server.endpoint, "CAST_TOKEN": token,
                                  "CONNECT_OPTION_COMPONENT_ID": "planner", "CONNECT_OPTION_SUBARCHITECTURE": "vision"})
    assert status == 0 and out["component"] == "planner", out


def test_connect_with_a_token_that_is_no_cast_token_is_refused_by_the_server(server: Any) -> None:
    # The format before JWTs: the client does not decode tokens, the server says what is wrong with it.
    status, out = connect_script({"CAST_ENDPOINT": server.endpoint, "CAST_TOKEN": "eyJjIjoicCJ9.c2ln"})
    assert status == 1 and out["error"] == "UnauthenticatedError", out
    assert out["message"].startswith("the server refused the token from CAST_TOKEN: "), out
    assert "format before JWTs" in out["message"], out
