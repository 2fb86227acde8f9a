"""Bad input to `cast foxglove` and `cast run --foxglove`: a malformed address or a taken port is named with what to
do, exit 2, and nothing is started; so is a system that does not answer or an unknown SA. The address parser's
accepted forms, without servers."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from cast.errors import InvalidArgumentError
from cast.foxglove.address import parse_foxglove_listen as parse_listen
from cast.listen import ListenAddress
from tests.conftest import ServerHandle
from tests.recording.conftest import cast


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A port something else listens on (bound on port 0, so never a fixed one)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


@pytest.mark.parametrize("listen", ["nonsense", "127.0.0.1:", "127.0.0.1:99999", "::1:8765", "host:port", ""])
def test_a_malformed_listen_address_is_named_with_what_to_give(server: ServerHandle, listen: str) -> None:
    out = cast("foxglove", "--endpoint", server.endpoint, "--listen", listen)
    assert out.returncode == 2, out.stderr
    assert f"--listen {listen!r}" in out.stderr and "HOST:PORT" in out.stderr and "127.0.0.1:0" in out.stderr
    assert "listening on" not in out.stdout


def test_a_taken_port_is_named_with_what_to_do(server: ServerHandle, taken_port: int) -> None:
    out = cast("foxglove", "--endpoint", server.endpoint, "--listen", f"127.0.0.1:{taken_port}")
    assert out.returncode == 2, out.stderr
    assert f"cannot listen on 127.0.0.1:{taken_port}: the address is in use" in out.stderr
    assert "--listen 127.0.0.1:0" in out.stderr
    assert "listening on" not in out.stdout


def test_an_address_not_of_this_machine_is_refused() -> None:
    out = cast("foxglove", "--endpoint", "127.0.0.1:1", "--listen", "nonexistent.invalid:0")
    assert out.returncode == 2 and "cannot listen on nonexistent.invalid:0" in out.stderr, out.stderr


def test_no_system_or_an_unknown_sa_is_a_clear_error(server: ServerHandle) -> None:
    with socket.socket() as s:  # a port nobody listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        nobody = f"127.0.0.1:{s.getsockname()[1]}"
        out = cast("foxglove", "--endpoint", nobody, "--listen", "127.0.0.1:0")
    assert out.returncode == 2 and f"no system answers at {nobody}" in out.stderr, out.stderr
    out = cast("foxglove", "--endpoint", server.endpoint, "--listen", "127.0.0.1:0", "--sa", "nope")
    assert out.returncode == 2 and "no subarchitecture 'nope'" in out.stderr and "vision" in out.stderr, out.stderr


def test_cast_run_refuses_a_bad_or_taken_address_before_starting_anything(tmp_path: Path, taken_port: int) -> None:
    config = tmp_path / "system.yaml"
    config.write_text("system: t\nsubarchitectures:\n  vision: {}\n")
    runtime = tmp_path / "runtime"
    for value, said in ((f"127.0.0.1:{taken_port}", f"cannot listen on 127.0.0.1:{taken_port}: the address is in "
                                                     "use"),
                        ("127.0.0.1:x", "--foxglove '127.0.0.1:x': give HOST:PORT")):
        out = cast("run", str(config), "--no-status", "--for", "1", "--runtime-dir", str(runtime),
                   f"--foxglove={value}")
        assert out.returncode == 2, out.stdout + out.stderr
        assert said in out.stderr
        assert "system 't'" not in out.stdout and not (runtime / "system.json").exists()


@pytest.mark.parametrize(("text", "expected"), [
    ("8765", ListenAddress("127.0.0.1", 8765)),
    ("127.0.0.1:0", ListenAddress("127.0.0.1", 0)),
    ("0.0.0.0:8765", ListenAddress("0.0.0.0", 8765)),
    ("[::1]:9000", ListenAddress("::1", 9000)),
    ("localhost:8765", ListenAddress("localhost", 8765)),
])
def test_the_listen_forms(text: str, expected: ListenAddress) -> None:
    assert parse_listen(text) == expected


def test_who_can_connect_and_the_url() -> None:
    assert parse_listen("127.0.0.2:1").loopback and parse_listen("[::1]:1").loopback
    assert parse_listen("localhost:1").loopback
    assert not parse_listen("0.0.0.0:1").loopback and not parse_listen("robot.local:1").loopback
    assert parse_listen("[::1]:0").url("ws", 4242) == "ws://[::1]:4242"
    with pytest.raises(InvalidArgumentError, match="--foxglove '65536'"):
        parse_listen("65536", "--foxglove")
