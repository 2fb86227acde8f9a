"""``cast export --to kubernetes``: plain manifests and a ``kustomization.yaml`` (docs/deploy.md).

One file per thing, each holding its objects:

- ``namespace.yaml``: the namespace (not for ``default`` or ``kube-*``);
- ``secrets.yaml``: the system secret and, with ``tls:``, the TLS Secrets (mode 0600);
- ``server-NAME.yaml``: a server's Service and its Deployment, or its StatefulSet
  with a volume claim when it keeps a journal (``persistence:``); probes on the
  gRPC health service (kubelet's ``grpc`` probe, or, with TLS, which kubelet's
  probe does not speak, ``python -m cast.export.health_probe`` in the container);
- ``ID.yaml``: a component's Deployment or Job (:mod:`cast.export.pods`);
- ``kustomization.yaml``: every file above, for ``kubectl apply -k DIR``.

Servers run ``cast serve CONFIG --server NAME`` from the image's checkout with
every variable the export resolved as ``--set`` (so the cluster sees the file
as the export did), on the configured port (7000 for port 0), told where the
other servers' SAs are with ``--route``. In-process components run inside
their server, as with ``cast run``; ``manual`` components are not exported.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cast.config.engines import IMAGE_ROOT, component_object, in_image, kube_name, server_object
from cast.config.model import ServerConfig, SystemConfig
from cast.export.files import OutputFile, yaml_documents
from cast.export.images import image_path
from cast.export.pods import (
    SECRET_DIR,
    TLS_DIR,
    PodContext,
    client_tls_env,
    component_workload,
    container_security,
    env_list,
    pod_security,
    secret_volume,
    tmp_volume,
)
from cast.export.secrets import (
    SECRET_KEY,
    SECRETS_FILE,
    SYSTEM_SECRET,
    TLS_CLIENT_SECRET,
    TLS_SERVER_SECRET,
    fingerprint,
    read_files,
    secret_object,
    tls_client_files,
    tls_server_files,
)

__all__ = ["DEFAULT_PORT", "KubernetesOptions", "kubernetes_files", "server_port"]

DEFAULT_PORT = 7000  # a server with port 0 in listen: (Services need a fixed port)


@dataclass(frozen=True)
class KubernetesOptions:
    """What the command line adds to the configuration."""

    namespace: str
    root: Path  # the checkout the images are built from
    secret: bytes
    volume_size: str = "1Gi"
    command: str = "cast export"  # as run, for the files' header


def server_port(server: ServerConfig) -> int:
    """The port a server listens on in its pod: its configured one, or 7000 for port 0."""
    port = int(server.listen.rpartition(":")[2])
    return port or DEFAULT_PORT


def kubernetes_files(config: SystemConfig, options: KubernetesOptions) -> list[OutputFile]:
    """Every file of the export, kustomization.yaml last."""
    directory = config.servers[0]
    ctx = PodContext(config=config, root=options.root, namespace=options.namespace,
                     system_label=kube_name(config.name) or "cast",
                     endpoint=f"{server_object(directory)}:{server_port(directory)}",
                     config_path=image_path(Path(config.source), options.root),
                     secret_hash=fingerprint(options.secret))
    header = (f"Written by `{options.command}` from {config.source}.\n"
              "Export again rather than editing (docs/deploy.md); change what the configuration cannot say with "
              "kustomize patches.")
    files: list[OutputFile] = []
    if options.namespace != "default" and not options.namespace.startswith("kube-"):
        namespace = {"apiVersion": "v1", "kind": "Namespace",
                     "metadata": {"name": options.namespace, "labels": ctx.labels("namespace", options.namespace)}}
        files.append(OutputFile("namespace.yaml", yaml_documents(header, [namespace])))
    files.append(OutputFile(SECRETS_FILE, yaml_documents(header, _secrets(ctx, options.secret)), private=True))
    for server in config.servers:
        files.append(OutputFile(f"{server_object(server)}.yaml", yaml_documents(header, _server(ctx, server,
                                                                                                  options))))
    for comp in config.components:
        if comp.launched:
            files.append(OutputFile(f"{component_object(comp)}.yaml",
                                    yaml_documents(header, [component_workload(ctx, comp)])))
    kustomization = {
        "apiVersion": "kustomize.config.k8s.io/v1beta1",
        "kind": "Kustomization",
        "namespace": options.namespace,
        "resources": [f.name for f in files],
    }
    files.append(OutputFile("kustomization.yaml", yaml_documents(header, [kustomization])))
    return files


def _secrets(ctx: PodContext, secret: bytes) -> list[dict[str, Any]]:
    labels = ctx.labels("secret", SYSTEM_SECRET)
    out = [secret_object(SYSTEM_SECRET, {SECRET_KEY: secret}, labels, ctx.namespace)]
    tls = ctx.config.tls
    if tls is not None:
        out.append(secret_object(TLS_SERVER_SECRET, read_files(tls_server_files(tls)),
                                 ctx.labels("secret", TLS_SERVER_SECRET), ctx.namespace))
        out.append(secret_object(TLS_CLIENT_SECRET, read_files(tls_client_files(tls)),
                                 ctx.labels("secret", TLS_CLIENT_SECRET), ctx.namespace))
    return out


def _server_command(ctx: PodContext, server: ServerConfig) -> list[str]:
    config = ctx.config
    argv = ["cast", "serve", ctx.config_path, "--server", server.name,
            "--listen", f"0.0.0.0:{server_port(server)}", "--secret-file", f"{SECRET_DIR}/{SECRET_KEY}",
            "--lease-ms", str(config.orchestrator.lease_ms)]
    for name, value in config.variables.items():
        argv += ["--set", f"{name}={value}"]
    for other in config.servers:
        if other is not server:
            for sa in other.subarchitectures:
                argv += ["--route", f"{sa}={server_object(other)}:{server_port(other)}"]
    return argv


def _probes(ctx: PodContext, server: ServerConfig) -> dict[str, Any]:
    """Readiness, liveness and start-up probes on the gRPC health service."""
    port = server_port(server)
    if ctx.config.tls is None:
        check: dict[str, Any] = {"grpc": {"port": port}}
    else:
        # kubelet's grpc probe speaks plaintext only: ask the health service over TLS from inside the container.
        tls = client_tls_env(ctx.config)
        argv = ["python", "-m", "cast.export.health_probe", f"127.0.0.1:{port}", "--server-name",
                server_object(server), "--ca", tls["CAST_TLS_CA"]]
        if "CAST_TLS_CERT" in tls:
            argv += ["--cert", tls["CAST_TLS_CERT"], "--key", tls["CAST_TLS_KEY"]]
        check = {"exec": {"command": argv}}
    return {
        "startupProbe": {**check, "periodSeconds": 2, "failureThreshold": 150},  # a long journal may take minutes
        "readinessProbe": {**check, "periodSeconds": 5, "failureThreshold": 2},
        "livenessProbe": {**check, "periodSeconds": 10, "failureThreshold": 3, "timeoutSeconds": 5},
    }


def _server(ctx: PodContext, server: ServerConfig, options: KubernetesOptions) -> list[dict[str, Any]]:
    """A server's Service, then its Deployment or (with a journal) StatefulSet."""
    config = ctx.config
    name = server_object(server)
    labels = ctx.labels("server", name, **{"cast/server": kube_name(server.name)})
    port = server_port(server)
    service = {
        "apiVersion": "v1",
        "kind": "Service",
        "metadata": ctx.metadata(name, labels),
        "spec": {"selector": ctx.selector(name),
                 "ports": [{"name": "grpc", "port": port, "targetPort": "grpc"}]},
    }
    tmp, tmp_mount = tmp_volume()
    mounts: list[dict[str, Any]] = [{"name": "system-secret", "mountPath": SECRET_DIR, "readOnly": True}, tmp_mount]
    volumes = [secret_volume("system-secret", SYSTEM_SECRET), tmp]
    if config.tls is not None:
        # cast serve reads the files the configuration names: each is mounted where the image has that path.
        for key, path in tls_server_files(config.tls).items():
            mounts.append({"name": "tls-server", "mountPath": image_path(path, ctx.root), "subPath": key,
                           "readOnly": True})
        mounts.append({"name": "tls", "mountPath": TLS_DIR, "readOnly": True})  # the health probe's client side
        volumes += [secret_volume("tls-server", TLS_SERVER_SECRET), secret_volume("tls", TLS_CLIENT_SECRET)]
    journal_dir = None
    if server.persistence is not None:
        journal_dir = in_image(server.persistence.path.parent, ctx.root) or server.persistence.path.parent
        mounts.append({"name": "journal", "mountPath": str(journal_dir)})
    container = {
        "name": "server",
        "image": config.images.python,
        "imagePullPolicy": config.images.pull_policy,
        "command": _server_command(ctx, server),
        "workingDir": str(IMAGE_ROOT),
        "env": env_list({"HOME": "/tmp", "PYTHONUNBUFFERED": "1"}),
        "ports": [{"name": "grpc", "containerPort": port}],
        **_probes(ctx, server),
        "securityContext": container_security(),
        "volumeMounts": mounts,
    }
    template = {
        "metadata": ctx.pod_metadata(labels),
        "spec": {
            "automountServiceAccountToken": False,
            "enableServiceLinks": False,
            "terminationGracePeriodSeconds": ctx.grace_seconds,
            **ctx.node_selector(server.host),
            "securityContext": pod_security(),
            "containers": [container],
            "volumes": volumes,
        },
    }
    spec: dict[str, Any] = {"replicas": 1, "selector": {"matchLabels": ctx.selector(name)}, "template": template}
    if journal_dir is None:
        # One server at a time: two would each hold half of the system's writes.
        workload = {"apiVersion": "apps/v1", "kind": "Deployment", "metadata": ctx.metadata(name, labels),
                    "spec": {**spec, "strategy": {"type": "Recreate"}, "revisionHistoryLimit": 3}}
    else:
        storage = {"requests": {"storage": options.volume_size}}
        claim = {"metadata": {"name": "journal", "labels": labels},
                 "spec": {"accessModes": ["ReadWriteOnce"], "resources": storage}}
        workload = {"apiVersion": "apps/v1", "kind": "StatefulSet", "metadata": ctx.metadata(name, labels),
                    "spec": {**spec, "serviceName": name, "volumeClaimTemplates": [claim]}}
    return [service, workload]
