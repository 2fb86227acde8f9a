"""Shared by the export tests: a checkout with a configuration that uses every feature, running cast export
in this process (as `cast` would: main(argv), in a working directory), and reading the manifests back."""

from __future__ import annotations

import contextlib
import io
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from cast.cli.main import main

# Everything an export maps: two servers (one durable, on a fixed port), TLS with client certificates, expiring
# tokens, a host, all four languages, an image of its own, in-process, manual and restart: never components,
# names that must be made Kubernetes names, variables.
FULL = """\
    system: Robot System_1
    variables: {SPEED: "3"}
    python_path: [components]
    auth: {token_ttl: 6}
    tls: {ca: certs/ca.pem, cert: certs/server.pem, key: certs/server.key, client_auth: true,
          client_cert: certs/client.pem, client_key: certs/client.key}
    orchestrator: {stop_timeout: 7, lease_ms: 4000}
    hosts: {arm: 10.0.0.12:7070}
    images:
      python: registry.example:5000/robot/cast-python:0.1.0
      pull_policy: Always
      components: {node_1: registry.example:5000/robot/node-comp:1}
    servers:
      main: {listen: 0.0.0.0:0, advertise: 10.0.0.10:0, subarchitectures: [vision, language]}
      far: {listen: 0.0.0.0:7100, subarchitectures: [motor],
            persistence: {path: data/far/journal.sqlite, durability: always}}
    subarchitectures:
      vision:
        components:
          Writer_1: {class: "tiny:Writer", args: {speed: "${SPEED}"}}
          watcher: {class: "tiny:Writer", privileged: true, host: arm}
          inproc: {class: "tiny:Writer", in_process: true}
          later: {class: "tiny:Writer", manual: true}
          once: {class: "tiny:Writer", restart: never}
      language:
        components:
          seg: {language: cpp, run: bin/seg}
          col: {language: java, class: a.B, classpath: [jars/x.jar]}
          node_1: {language: other, run: "node comp.js"}
      motor:
        task_manager: {policy: fifo, max_concurrent: 1}
        components:
          mover: {class: "tiny:Writer", restart: always}
    """
FULL_FILES = ("certs/ca.pem", "certs/server.pem", "certs/server.key", "certs/client.pem", "certs/client.key")


def checkout(root: Path, text: str = FULL, files: tuple[str, ...] = FULL_FILES) -> Path:
    """A checkout at ``root`` with ``system.yaml`` (``text``, dedented) and the named files; the config's path."""
    root.mkdir(parents=True, exist_ok=True)
    for name in files:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(f"contents of {name}\n")
    config = root / "system.yaml"
    config.write_text(textwrap.dedent(text))
    return config


@dataclass
class Result:
    """What `cast ...` printed and returned."""

    code: int
    out: str
    err: str


def cast(cwd: Path, *argv: str) -> Result:
    """Run ``cast ARGV`` in this process, in ``cwd``."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.chdir(cwd), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return Result(code, out.getvalue(), err.getvalue())


def documents(out_dir: Path) -> dict[str, list[dict[str, Any]]]:
    """Every YAML file of an export, by name, as its documents."""
    return {p.name: [d for d in yaml.safe_load_all(p.read_text()) if d is not None]
            for p in sorted(out_dir.glob("*.yaml"))}


def objects(out_dir: Path) -> list[dict[str, Any]]:
    """Every Kubernetes object of an export (the kustomization left out)."""
    return [d for name, docs in documents(out_dir).items() if name != "kustomization.yaml" for d in docs]


def pod_spec(obj: dict[str, Any]) -> dict[str, Any]:
    """The pod spec of a workload."""
    spec: dict[str, Any] = obj["spec"]["template"]["spec"]
    return spec


def workloads(out_dir: Path) -> dict[str, dict[str, Any]]:
    """Every workload (Deployment, StatefulSet, Job) by name."""
    return {o["metadata"]["name"]: o for o in objects(out_dir)
            if o["kind"] in ("Deployment", "StatefulSet", "Job")}
