"""cast export --to systemd: the units pass `systemd-analyze verify` (Debian's systemd, which make export-deps
installs when missing; this test fails without it rather than skipping), run cast run and one cast agent per host
with restart settings and hardening, and keep the secret a credential."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tests.conftest import ROOT, VENV_BIN
from tests.export.helpers import cast, checkout

HARDENING = {"NoNewPrivileges=yes", "ProtectSystem=strict", "ProtectHome=read-only", "PrivateTmp=yes",
             "ProtectKernelTunables=yes", "ProtectControlGroups=yes", "RestrictSUIDSGID=yes", "CapabilityBoundingSet=",
             "SystemCallArchitectures=native", "UMask=0077"}


def verify(unit: Path, tmp_path: Path, instance: str = "") -> None:
    """`systemd-analyze verify` on ``unit`` (a template as an instance of it): no error, no warning about it."""
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is missing: `make export-deps` installs Debian's systemd"
    if instance:
        copy = tmp_path / "verify" / unit.name.replace("@.", f"@{instance}.")
        copy.parent.mkdir(exist_ok=True)
        copy.write_text(unit.read_text())
        unit = copy
    done = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    complaints = [line for line in (done.stdout + done.stderr).splitlines() if unit.name in line]
    assert done.returncode == 0 and not complaints, done.stdout + done.stderr


@pytest.fixture(scope="module")
def multihost(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("systemd") / "out"
    result = cast(ROOT, "export", "configs/demo-multihost.yaml", "--to", "systemd", "-o", str(out), "--user", "cast")
    assert result.code == 0, result.err
    return out


def lines(path: Path) -> set[str]:
    return set(path.read_text().splitlines())


def test_every_unit_of_the_multi_host_demo_passes_systemd_analyze_verify(multihost: Path, tmp_path: Path) -> None:
    assert sorted(str(p.relative_to(multihost)) for p in multihost.rglob("*.service")) == [
        "local/cast-system@.service", "robot/cast-agent.service", "workstation/cast-agent.service"]
    verify(multihost / "local" / "cast-system@.service", tmp_path, instance="scene-description")
    for host in ("robot", "workstation"):
        verify(multihost / host / "cast-agent.service", tmp_path)


def test_the_verification_catches_a_broken_unit(multihost: Path, tmp_path: Path) -> None:
    broken = tmp_path / "cast-agent.service"
    broken.write_text((multihost / "robot" / "cast-agent.service").read_text().replace("Restart=", "Restrat="))
    with pytest.raises(AssertionError, match="Unknown key"):
        verify(broken, tmp_path)
    missing = tmp_path / "missing.service"
    missing.write_text((multihost / "robot" / "cast-agent.service").read_text().replace(
        str(ROOT / ".venv" / "bin" / "cast"), "/nonexistent/cast"))
    with pytest.raises(AssertionError, match="not executable"):
        verify(missing, tmp_path)


def test_the_system_unit_runs_cast_run_restarts_on_failure_and_is_hardened(multihost: Path) -> None:
    unit = lines(multihost / "local" / "cast-system@.service")
    assert f"ExecStart={ROOT}/.venv/bin/cast run ${{CAST_CONFIG}} --runtime-dir %t/cast/%i --no-status" in unit
    assert {f"WorkingDirectory={ROOT}", "User=cast", "EnvironmentFile=/etc/cast/%i.env", "Restart=on-failure",
            "RestartPreventExitStatus=2", "KillMode=mixed", "LoadCredential=secret:/etc/cast/secret",
            "Environment=CAST_SECRET_FILE=%d/secret", "WantedBy=multi-user.target"} <= unit
    assert HARDENING <= unit
    env = lines(multihost / "local" / "scene-description.env")
    assert {"CAST_CONFIG=configs/demo-multihost.yaml", "ROBOT_ADDRESS=127.0.0.1", "SEGMENTER_LANGUAGE=cpp"} <= env


def test_one_agent_unit_per_host_listening_where_the_configuration_says(multihost: Path) -> None:
    for host, port in (("robot", 7071), ("workstation", 7072)):
        unit = lines(multihost / host / "cast-agent.service")
        start = next(line for line in unit if line.startswith("ExecStart="))
        assert start == (f"ExecStart={ROOT}/.venv/bin/cast agent --listen 127.0.0.1:{port} --root {ROOT} "
                         "--secret-file %d/secret --log-dir %L/cast-agent")
        assert {"Restart=always", "LoadCredential=secret:/etc/cast/secret", "LogsDirectory=cast-agent"} <= unit
        assert HARDENING <= unit


def test_agents_with_tls_and_servers_with_journals_get_their_credentials_and_writable_paths(tmp_path: Path) -> None:
    config = checkout(tmp_path / "co", """\
        system: tls robot
        hosts:
          arm: {agent: "10.0.0.12:7070", tls: {ca: certs/ca.pem, cert: certs/orch.pem, key: certs/orch.key}}
          cam: {agent: "10.0.0.13:7070", tls: {ca: certs/ca.pem}}
        servers:
          main: {listen: 10.0.0.10:7000, subarchitectures: [v], persistence: {path: data/main.sqlite}}
          far: {listen: 10.0.0.12:7001, host: arm, subarchitectures: [w], persistence: {path: /srv/far/j.sqlite}}
        subarchitectures:
          v: {components: {a: {class: "m:A", host: cam}}}
          w: {}
        """, files=())
    result = cast(config.parent, "export", "system.yaml", "--to", "systemd", "-o", "out", "--root", "/opt/robot",
                  "--cast", str(VENV_BIN / "cast"))
    assert result.code == 0, result.err
    out = config.parent / "out"
    arm, cam = lines(out / "arm" / "cast-agent.service"), lines(out / "cam" / "cast-agent.service")
    arm_start = next(line for line in arm if line.startswith("ExecStart="))
    assert "--tls-cert %d/agent.pem --tls-key %d/agent.key --tls-ca %d/client-ca.pem" in arm_start  # mutual TLS
    cam_start = next(line for line in cam if line.startswith("ExecStart="))
    assert "--tls-cert %d/agent.pem" in cam_start and "--tls-ca" not in cam_start
    assert "ReadWritePaths=-/srv/far" in arm and not any(line.startswith("ReadWritePaths") for line in cam)
    system = lines(out / "local" / "cast-system@.service")
    assert "ReadWritePaths=-/opt/robot/data" in system and "WorkingDirectory=/opt/robot" in system
    assert (out / "local" / "tls-robot.env").exists()  # the instance: the system's name, made a unit name
    for unit in (out / "arm" / "cast-agent.service", out / "cam" / "cast-agent.service"):
        verify(unit, tmp_path)
    verify(out / "local" / "cast-system@.service", tmp_path, instance="tls-robot")
