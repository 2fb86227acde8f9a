"""``cast export CONFIG --to kubernetes|systemd -o DIR``: a system as a cluster engine's files (docs/deploy.md)."""

from __future__ import annotations

import argparse
import getpass
import os
import re
import shlex
import sys
from pathlib import Path
from typing import Any

import yaml

from cast.cli.options import parse_sets
from cast.config.engines import ENGINES, component_object, kube_name, read_for_engine, server_object
from cast.config.model import SystemConfig
from cast.errors import InvalidArgumentError
from cast.export.files import OutputFile, write_output
from cast.export.kubernetes import KubernetesOptions, kubernetes_files, server_port
from cast.export.secrets import SECRETS_FILE, find_system_secret
from cast.export.systemd import SECRET_PATH, SystemdOptions, instance_name, systemd_files
from cast.export.validate import validate_objects

__all__ = ["add_commands"]

_DNS_LABEL = re.compile(r"[a-z0-9]([-a-z0-9]{0,61}[a-z0-9])?\Z")
_QUANTITY = re.compile(r"[1-9][0-9]*(\.[0-9]+)?(Ki|Mi|Gi|Ti|Pi|Ei|k|M|G|T|P|E)?\Z")


def _export(args: argparse.Namespace) -> int:
    kubernetes = args.to == "kubernetes"
    for option, value in (("--namespace", args.namespace), ("--volume-size", args.volume_size),
                          ("--secret-file", args.secret_file), ("--validate", args.validate or None)):
        if value is not None and not kubernetes:
            raise InvalidArgumentError(f"{option} is for --to kubernetes only")
    for option, value in (("--root", args.root), ("--cast", args.cast), ("--user", args.user)):
        if value is not None and kubernetes:
            raise InvalidArgumentError(f"{option} is for --to systemd only")
    here = Path.cwd()
    config, problems = read_for_engine(args.config, args.to, here, parse_sets(args.set))
    for problem in sorted(problems.items, key=lambda p: (p.warning, p.position.file, p.position.line)):
        print(problem, file=sys.stderr)
    if config is None or problems.errors:
        count = len(problems.errors)
        print(f"cast export: {args.config} has {count} error{'s' if count != 1 else ''}; nothing was written",
              file=sys.stderr)
        return 2
    out = Path(args.output)
    command = shlex.join(["cast", "export", args.config, "--to", args.to,
                          *(["--namespace", args.namespace] if args.namespace else []),
                          *(item for name in args.set for item in ("--set", name))])
    if kubernetes:
        files, lines = _kubernetes(config, args, here, out, command)
        for version in args.validate:
            lines.append(_validated(files, version))
    else:
        files, lines = _systemd(config, args, here, command)
    write_output(out, files, args.to, args.config)
    print(f"cast export: {args.config} -> {out}/ ({args.to}): {len(files)} files")
    for line in lines:
        print(f"  {line}")
    return 0


def _kubernetes(config: SystemConfig, args: argparse.Namespace, here: Path, out: Path,
                command: str) -> tuple[list[OutputFile], list[str]]:
    namespace = args.namespace or kube_name(config.name)[:63].strip("-") or "cast"
    if not _DNS_LABEL.match(namespace):
        raise InvalidArgumentError(f"--namespace {namespace!r} is no Kubernetes namespace name: 1 to 63 lower-case "
                                   "letters, digits and '-', starting and ending with a letter or digit")
    size = args.volume_size or "1Gi"
    if not _QUANTITY.match(size):
        raise InvalidArgumentError(f"--volume-size {size!r}: give a Kubernetes quantity such as 1Gi, 500Mi or 10G")
    secret = find_system_secret(args.secret_file, os.environ, out)
    options = KubernetesOptions(namespace=namespace, root=here, secret=secret.value,
                                volume_size=size, command=command)
    files = kubernetes_files(config, options)
    images = config.images
    lines = [f"namespace {namespace}; the directory (what components dial): "
             f"{server_object(config.servers[0])}:{server_port(config.servers[0])}"]
    for server in config.servers:
        kind = "StatefulSet with a volume" if server.persistence is not None else "Deployment"
        lines.append(f"{server_object(server)}.yaml: server '{server.name}' ({', '.join(server.subarchitectures)}): "
                     f"Service and {kind}, image {images.python}")
    for comp in config.components:
        if comp.launched:
            kind = "Job (restart: never)" if comp.restart.mode == "never" else "Deployment"
            lines.append(f"{component_object(comp)}.yaml: component '{comp.id}' ({comp.language}): {kind}, image "
                         f"{images.for_component(comp)}")
    skipped = [f"'{c.id}' (in process, inside server '{config.server_of(c.subarchitecture).name}')"
               for c in config.components if c.in_process]
    skipped += [f"'{c.id}' (manual: start it by hand with `cast token`)" for c in config.components if c.manual]
    if skipped:
        lines.append(f"no workload of its own: {', '.join(skipped)}")
    lines.append(f"{SECRETS_FILE}: the system secret ({secret.origin}){' and the TLS files' if config.tls else ''}; "
                 "mode 0600: keep it out of version control")
    lines.append("next: build and load the images (docs/deploy.md, \"Images\"), then: kubectl apply -k "
                 f"{shlex.quote(str(out))}")
    return files, lines


def _validated(files: list[OutputFile], version: str) -> str:
    """``--validate VERSION``: every object checked against that Kubernetes version's schemas, or refused."""
    objects = [doc for f in files if f.name != "kustomization.yaml" for doc in yaml.safe_load_all(f.text) if doc]
    problems = validate_objects(objects, version)
    if problems:
        raise InvalidArgumentError("\n".join([*problems, f"the manifests are not valid for Kubernetes {version} "
                                                         "(above); nothing was written"]))
    return f"valid for Kubernetes {version}: {len(objects)} objects (kubernetes-validate, strict)"


def _systemd(config: SystemConfig, args: argparse.Namespace, here: Path,
             command: str) -> tuple[list[OutputFile], list[str]]:
    target = Path(args.root) if args.root else here
    if not target.is_absolute():
        raise InvalidArgumentError(f"--root {args.root}: give the checkout's absolute path on the hosts")
    cast = Path(args.cast) if args.cast else target / ".venv" / "bin" / "cast"
    if not cast.is_absolute():
        raise InvalidArgumentError(f"--cast {args.cast}: give the absolute path of the cast command on the hosts")
    options = SystemdOptions(root=here, target_root=target, cast=cast, user=args.user or getpass.getuser(),
                             command=command)
    files = systemd_files(config, options)
    instance = instance_name(config)
    lines = [f"local/cast-system@.service and local/{instance}.env: `cast run` of the system, as user "
             f"{options.user}, in {target}"]
    lines += [f"{h.name}/cast-agent.service: `cast agent` on host '{h.name}', listening on {h.agent}"
              for h in config.hosts.values()]
    lines.append(f"next, on every host: the system secret in {SECRET_PATH} (mode 0600); the host's units in "
                 "/etc/systemd/system; then `systemctl enable --now cast-agent` on each host of hosts:, and on this "
                 f"one: install local/{instance}.env as /etc/cast/{instance}.env and "
                 f"`systemctl enable --now cast-system@{instance}` (docs/deploy.md, \"systemd\")")
    return files, lines


def add_commands(sub: Any) -> None:
    """Add ``cast export``."""
    export = sub.add_parser("export", help="write a system as Kubernetes manifests or systemd units "
                                           "(docs/deploy.md)")
    export.add_argument("config", help="system configuration (YAML), in the checkout (run from the checkout's root)")
    export.add_argument("--to", required=True, choices=ENGINES, help="the engine to write files for")
    export.add_argument("-o", "--output", required=True, metavar="DIR",
                        help="directory to write into: new, empty, or an earlier export's (whose files are replaced)")
    export.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="set a config variable")
    k8s = export.add_argument_group("kubernetes")
    k8s.add_argument("--namespace", help="the namespace of every object (default: the system's name)")
    k8s.add_argument("--secret-file", help="the system secret (default: $CAST_SECRET, $CAST_SECRET_FILE, the earlier "
                                           "export's in DIR, else a new one)")
    k8s.add_argument("--volume-size", help="the size of a durable server's volume (default 1Gi)")
    k8s.add_argument("--validate", action="append", default=[], metavar="VERSION",
                     help="check every manifest against the schemas of this Kubernetes version (e.g. 1.30; "
                          "repeatable) before writing; needs kubernetes-validate (the export extra)")
    systemd = export.add_argument_group("systemd")
    systemd.add_argument("--root", help="the checkout's absolute path on the hosts (default: the current directory)")
    systemd.add_argument("--cast", help="the cast command on the hosts (default: ROOT/.venv/bin/cast, what make "
                                        "setup installs)")
    systemd.add_argument("--user", help="the user the services run as (default: you)")
    export.set_defaults(fn=_export)
