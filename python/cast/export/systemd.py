"""``cast export --to systemd``: unit files that run the system with ``cast run`` and ``cast agent``.

``DIR/local/`` holds ``cast-system@.service``, a template whose instance is the
system's name: it runs ``cast run $CAST_CONFIG`` in the checkout, reading
``/etc/cast/INSTANCE.env`` (``DIR/local/INSTANCE.env``: the configuration's path
and every variable the export resolved). ``DIR/HOST/cast-agent.service`` runs
``cast agent`` on each host of ``hosts:``, listening on the address the
configuration gives it. The system secret is a systemd credential
(``LoadCredential=secret:/etc/cast/secret``), readable by the service alone.

Every unit restarts on failure (``cast run`` exits 2 for a configuration that
is wrong, which no restart mends: ``RestartPreventExitStatus=2``), stops its
children itself (``KillMode=mixed``: SIGTERM to ``cast run`` or the agent,
SIGKILL to what is left after the stop timeout) and is hardened: no new
privileges, no capabilities, the file system read-only but for the runtime,
log and journal directories, private /tmp, kernel and control groups
protected (docs/deploy.md, "systemd").
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from cast.config.model import LOCAL_HOST, HostConfig, SystemConfig
from cast.export.files import OutputFile

__all__ = ["SECRET_PATH", "SystemdOptions", "instance_name", "systemd_files"]

SECRET_PATH = "/etc/cast/secret"
AGENT_TLS_DIR = "/etc/cast/agent"

HARDENING = [
    ("NoNewPrivileges", "yes"),
    ("ProtectSystem", "strict"),
    ("ProtectHome", "read-only"),
    ("PrivateTmp", "yes"),
    # No PrivateDevices=: a robot's components use cameras, serial ports and GPUs (add it in a drop-in if not).
    ("ProtectKernelTunables", "yes"),
    ("ProtectKernelModules", "yes"),
    ("ProtectKernelLogs", "yes"),
    ("ProtectControlGroups", "yes"),
    ("ProtectClock", "yes"),
    ("ProtectHostname", "yes"),
    ("RestrictSUIDSGID", "yes"),
    ("RestrictRealtime", "yes"),
    ("RestrictNamespaces", "yes"),
    ("LockPersonality", "yes"),
    ("SystemCallArchitectures", "native"),
    ("CapabilityBoundingSet", ""),
    ("AmbientCapabilities", ""),
    ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6 AF_NETLINK"),
    ("UMask", "0077"),
]


@dataclass(frozen=True)
class SystemdOptions:
    """What the command line adds to the configuration."""

    root: Path  # the checkout here, where the configuration is read
    target_root: Path  # the checkout's path on the hosts the units run on
    cast: Path  # the cast command on those hosts
    user: str
    command: str = "cast export"


def instance_name(config: SystemConfig) -> str:
    """The template's instance for this system: its name, with what a unit name cannot hold made '-'."""
    return re.sub(r"[^A-Za-z0-9:_.-]", "-", config.name).strip("-") or "cast"


def systemd_files(config: SystemConfig, options: SystemdOptions) -> list[OutputFile]:
    """The units (and the environment file) of every host."""
    instance = instance_name(config)
    header = (f"Written by `{options.command}` from {config.source}.\n"
              "Export again rather than editing; add settings in a drop-in (systemctl edit).")
    # Relative to the checkout (WorkingDirectory), as cast run sends it to the agents.
    config_path = Path(config.source).resolve().relative_to(options.root.resolve())
    env_lines = [f"CAST_CONFIG={config_path}", *(f"{k}={_env_value(v)}" for k, v in config.variables.items())]
    files = [
        OutputFile(f"{LOCAL_HOST}/cast-system@.service", _system_unit(config, options, header)),
        OutputFile(f"{LOCAL_HOST}/{instance}.env",
                   "".join(f"# {line}\n" for line in header.splitlines())
                   + f"# Install as /etc/cast/{instance}.env: cast-system@{instance}.service reads it.\n"
                   + "\n".join(env_lines) + "\n"),
    ]
    for host in config.hosts.values():
        files.append(OutputFile(f"{host.name}/cast-agent.service", _agent_unit(config, host, options, header)))
    return files


def _on_host(path: Path, options: SystemdOptions) -> Path:
    """``path`` of the checkout here as the same file in the checkout on the hosts (else unchanged)."""
    try:
        return options.target_root / path.resolve().relative_to(options.root.resolve())
    except ValueError:
        return path.resolve()


def _env_value(value: str) -> str:
    """A value for an EnvironmentFile: quoted when it has spaces, quotes or a backslash."""
    return value if re.fullmatch(r"[A-Za-z0-9_.,:/@%+=-]*", value) else '"' + value.replace("\\", "\\\\").replace(
        '"', '\\"') + '"'


def _journal_dirs(config: SystemConfig, host: str, options: SystemdOptions) -> list[str]:
    """ReadWritePaths for the journals of the servers on ``host`` (``-``: a missing one is no error)."""
    return [f"-{_on_host(s.persistence.path.parent, options)}" for s in config.servers
            if s.persistence is not None and s.host == host]


def _render(header: str, sections: list[tuple[str, list[tuple[str, str]]]]) -> str:
    lines = [f"# {line}" for line in header.splitlines()]
    for name, entries in sections:
        lines += ["", f"[{name}]", *(f"{key}={value}" for key, value in entries)]
    return "\n".join(lines) + "\n"


def _system_unit(config: SystemConfig, options: SystemdOptions, header: str) -> str:
    stop = config.orchestrator.stop_timeout
    launched = sum(1 for c in config.components if c.launched)
    service = [
        ("Type", "exec"),
        ("User", options.user),
        ("WorkingDirectory", str(options.target_root)),
        ("EnvironmentFile", "/etc/cast/%i.env"),
        ("LoadCredential", f"secret:{SECRET_PATH}"),
        ("Environment", "CAST_SECRET_FILE=%d/secret"),
        ("RuntimeDirectory", "cast/%i"),  # the runtime directory: system.json, logs, token files
        ("ExecStart", f"{options.cast} run ${{CAST_CONFIG}} --runtime-dir %t/cast/%i --no-status"),
        ("Restart", "on-failure"),
        ("RestartSec", "5"),
        ("RestartPreventExitStatus", "2"),
        ("KillMode", "mixed"),
        # cast run stops components one by one in reverse order, each within stop_timeout.
        ("TimeoutStopSec", f"{int(stop * max(1, launched) + 15)}"),
        *HARDENING,
        *(("ReadWritePaths", path) for path in _journal_dirs(config, LOCAL_HOST, options)),
    ]
    return _render(header, [
        ("Unit", [("Description", f"CAST system %i ({config.name}): cast run"),
                  ("Documentation", f"file://{options.target_root}/docs/deploy.md"),
                  ("After", "network-online.target"), ("Wants", "network-online.target")]),
        ("Service", service),
        ("Install", [("WantedBy", "multi-user.target")]),
    ])


def _agent_unit(config: SystemConfig, host: HostConfig, options: SystemdOptions, header: str) -> str:
    argv = [str(options.cast), "agent", "--listen", host.agent, "--root", str(options.target_root),
            "--secret-file", "%d/secret", "--log-dir", "%L/cast-agent"]
    credentials = [("LoadCredential", f"secret:{SECRET_PATH}")]
    if host.tls_ca is not None:
        # The configuration names the CA that signed the agent's certificate; the agent's own files live here.
        credentials += [("LoadCredential", f"agent.pem:{AGENT_TLS_DIR}/cert.pem"),
                        ("LoadCredential", f"agent.key:{AGENT_TLS_DIR}/key.pem")]
        argv += ["--tls-cert", "%d/agent.pem", "--tls-key", "%d/agent.key"]
        if host.tls_cert is not None:  # mutual TLS: the agent checks the orchestrator's client certificate
            credentials.append(("LoadCredential", f"client-ca.pem:{AGENT_TLS_DIR}/client-ca.pem"))
            argv += ["--tls-ca", "%d/client-ca.pem"]
    service = [
        ("Type", "exec"),
        ("User", options.user),
        ("WorkingDirectory", str(options.target_root)),
        *credentials,
        ("LogsDirectory", "cast-agent"),
        ("ExecStart", " ".join(argv)),
        ("Restart", "always"),
        ("RestartSec", "2"),
        ("KillMode", "mixed"),
        ("TimeoutStopSec", f"{int(config.orchestrator.stop_timeout + 15)}"),
        *HARDENING,
        *(("ReadWritePaths", path) for path in _journal_dirs(config, host.name, options)),
    ]
    return _render(header, [
        ("Unit", [("Description", f"CAST agent of host {host.name} (system {config.name}): cast agent"),
                  ("After", "network-online.target"), ("Wants", "network-online.target")]),
        ("Service", service),
        ("Install", [("WantedBy", "multi-user.target")]),
    ])
