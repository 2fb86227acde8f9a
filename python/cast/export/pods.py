"""Pod templates of an exported system: a component's pod and the parts every pod shares.

A component's pod (docs/deploy.md, "Tokens"):

- an init container ``token`` (image ``images.python``) runs ``cast token ID
  --write /var/run/cast/token/token``: the only place besides the servers where
  the system secret is mounted. It writes the component's token into an
  ``emptyDir`` (memory) the component shares;
- with ``auth.token_ttl``, a sidecar ``token-renewer`` (an init container with
  ``restartPolicy: Always``, Kubernetes 1.29 or newer) runs the same with
  ``--renew``: a fresh token every ttl / 3, as ``cast run`` renews a token file;
- the component's container runs its command directly (no shell: an image
  needs none) with ``CAST_TOKEN_FILE`` naming that file and no ``CAST_TOKEN``:
  every runner takes the token from the file when it is set, and reads it again
  whenever it changes, so the token is never in the process environment.

The rest of the launch contract is environment variables: ``CAST_ENDPOINT``
(the directory's Service), ``CAST_COMPONENT_ID``, ``CAST_SUBARCHITECTURE``,
``CAST_ARGS``, ``CAST_TLS_*`` (the components' TLS Secret) and a long
``CAST_CONNECT_WINDOW_S``, since a pod may start before its server is ready.
Every container runs as user 10001 (the images' ``cast``), without privileges,
on a read-only root file system with a ``/tmp`` of its own.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cast.config.engines import component_object, kube_name
from cast.config.model import ComponentConfig, SystemConfig
from cast.export.images import component_container
from cast.export.secrets import SECRET_KEY, SYSTEM_SECRET, TLS_CLIENT_SECRET, tls_client_files

__all__ = [
    "SECRET_DIR",
    "TLS_DIR",
    "TOKEN_FILE",
    "PodContext",
    "component_workload",
    "container_security",
    "pod_security",
]

SECRET_DIR = "/var/run/cast/secret"
TOKEN_DIR = "/var/run/cast/token"
TOKEN_FILE = f"{TOKEN_DIR}/token"
TLS_DIR = "/var/run/cast/tls"
USER_ID = 10001  # the user deploy/images/ create
CONNECT_WINDOW_S = "300"  # a component may start minutes before its server is ready (image pulls)
HOST_LABEL = "cast/host"


@dataclass(frozen=True)
class PodContext:
    """What every pod template of one export shares."""

    config: SystemConfig
    root: Path  # the checkout, which the images hold at /opt/cast
    namespace: str
    system_label: str
    endpoint: str  # the directory's Service and port, what components dial
    config_path: str  # the configuration in the images (under /opt/cast)
    secret_hash: str  # a short hash of the system secret (pods restart when it changes)

    def labels(self, role: str, name: str, **extra: str) -> dict[str, str]:
        """The labels of one object: the system, its role (server or component) and its name."""
        return {
            "app.kubernetes.io/name": "cast",
            "app.kubernetes.io/part-of": self.system_label,
            "app.kubernetes.io/component": role,
            "app.kubernetes.io/instance": name,
            "app.kubernetes.io/managed-by": "cast-export",
            **extra,
        }

    @property
    def grace_seconds(self) -> int:
        """Seconds between SIGTERM and SIGKILL: the stop timeout, in whole seconds (at least 1)."""
        return max(1, math.ceil(self.config.orchestrator.stop_timeout))

    def selector(self, name: str) -> dict[str, str]:
        """The labels that select one workload's pods."""
        return {"app.kubernetes.io/part-of": self.system_label, "app.kubernetes.io/instance": name}

    def metadata(self, name: str, labels: dict[str, str]) -> dict[str, Any]:
        """An object's metadata in the export's namespace."""
        return {"name": name, "namespace": self.namespace, "labels": labels}

    def pod_metadata(self, labels: dict[str, str]) -> dict[str, Any]:
        """A pod template's metadata: its labels, the configuration, the secret's hash."""
        return {"labels": labels, "annotations": {"cast/config": self.config_path,
                                                  "cast/secret-sha256": self.secret_hash}}

    def node_selector(self, host: str) -> dict[str, Any]:
        """``nodeSelector`` for a component or server placed on a host (none for local)."""
        return {} if host == "local" else {"nodeSelector": {HOST_LABEL: kube_name(host)}}


def pod_security() -> dict[str, Any]:
    """The pod's security context: the images' unprivileged user; volumes writable by its group."""
    return {"runAsNonRoot": True, "runAsUser": USER_ID, "runAsGroup": USER_ID, "fsGroup": USER_ID,
            "seccompProfile": {"type": "RuntimeDefault"}}


def container_security() -> dict[str, Any]:
    """A container's security context: no privileges, no capabilities, a read-only root file system."""
    return {"allowPrivilegeEscalation": False, "readOnlyRootFilesystem": True, "capabilities": {"drop": ["ALL"]}}


def secret_volume(name: str, secret: str) -> dict[str, Any]:
    """A volume of a Secret, readable by the pod's user and group only."""
    return {"name": name, "secret": {"secretName": secret, "defaultMode": 0o440}}


def tmp_volume() -> tuple[dict[str, Any], dict[str, Any]]:
    """A writable /tmp (the root file system is read-only): the volume and its mount."""
    return {"name": "tmp", "emptyDir": {}}, {"name": "tmp", "mountPath": "/tmp"}


def env_list(values: dict[str, str]) -> list[dict[str, str]]:
    """Environment variables in Kubernetes' form."""
    return [{"name": key, "value": value} for key, value in values.items()]


def client_tls_env(config: SystemConfig) -> dict[str, str]:
    """``CAST_TLS_*`` for a container that mounts the components' TLS Secret at /var/run/cast/tls."""
    if config.tls is None:
        return {}
    files = tls_client_files(config.tls)
    names = {"ca": "CAST_TLS_CA", "cert": "CAST_TLS_CERT", "key": "CAST_TLS_KEY"}
    return {names[key]: f"{TLS_DIR}/{key}" for key in files}


def _token_container(ctx: PodContext, comp: ComponentConfig, renew: bool) -> dict[str, Any]:
    ttl = ctx.config.auth.token_ttl
    argv = ["cast", "token", comp.id, "--sa", comp.subarchitecture, *(["--privileged"] if comp.privileged else []),
            "--endpoint", ctx.endpoint, "--secret-file", f"{SECRET_DIR}/{SECRET_KEY}", "--ttl", f"{ttl:g}",
            "--write", TOKEN_FILE, *(["--renew"] if renew else [])]
    container: dict[str, Any] = {
        "name": "token-renewer" if renew else "token",
        "image": ctx.config.images.python,
        "imagePullPolicy": ctx.config.images.pull_policy,
        "command": argv,
        "env": env_list({"HOME": "/tmp"}),
        "securityContext": container_security(),
        "volumeMounts": [{"name": "system-secret", "mountPath": SECRET_DIR, "readOnly": True},
                         {"name": "token", "mountPath": TOKEN_DIR}, tmp_volume()[1]],
    }
    if renew:
        container["restartPolicy"] = "Always"  # a native sidecar: runs beside the component, ends with it
    return container


def component_workload(ctx: PodContext, comp: ComponentConfig) -> dict[str, Any]:
    """A component's Deployment (restart ``always`` or ``on-failure``) or Job (``never``)."""
    config = ctx.config
    name = component_object(comp)
    labels = ctx.labels("component", name, **{"cast/subarchitecture": kube_name(comp.subarchitecture)})
    spec = component_container(comp, config, ctx.root)
    env = {
        "CAST_ENDPOINT": ctx.endpoint,
        "CAST_COMPONENT_ID": comp.id,
        "CAST_SUBARCHITECTURE": comp.subarchitecture,
        "CAST_ARGS": json.dumps(comp.args),
        "CAST_TOKEN_FILE": TOKEN_FILE,
        "CAST_CONNECT_WINDOW_S": CONNECT_WINDOW_S,
        **client_tls_env(config),
        **spec.env,
        "HOME": "/tmp",
    }
    tmp, tmp_mount = tmp_volume()
    mounts = [{"name": "token", "mountPath": TOKEN_DIR, "readOnly": True}, tmp_mount]
    volumes = [secret_volume("system-secret", SYSTEM_SECRET), {"name": "token", "emptyDir": {"medium": "Memory"}},
               tmp]
    if config.tls is not None:
        mounts.append({"name": "tls", "mountPath": TLS_DIR, "readOnly": True})
        volumes.append(secret_volume("tls", TLS_CLIENT_SECRET))
    init = [_token_container(ctx, comp, renew=False)]
    if config.auth.token_ttl > 0:
        init.append(_token_container(ctx, comp, renew=True))
    never = comp.restart.mode == "never"
    pod: dict[str, Any] = {
        "automountServiceAccountToken": False,
        "enableServiceLinks": False,  # no <SERVICE>_PORT variables beside the launch contract
        "terminationGracePeriodSeconds": ctx.grace_seconds,  # SIGTERM, then SIGKILL
        **ctx.node_selector(comp.host),
        "securityContext": pod_security(),
        "initContainers": init,
        "containers": [{
            "name": "component",
            "image": spec.image,
            "imagePullPolicy": config.images.pull_policy,
            "command": spec.argv,  # the token comes from CAST_TOKEN_FILE, which every runner reads
            "workingDir": spec.working_dir,
            "env": env_list(env),
            "securityContext": container_security(),
            "volumeMounts": mounts,
        }],
        "volumes": volumes,
        **({"restartPolicy": "Never"} if never else {}),
    }
    template = {"metadata": ctx.pod_metadata(labels), "spec": pod}
    if never:
        return {"apiVersion": "batch/v1", "kind": "Job", "metadata": ctx.metadata(name, labels),
                "spec": {"backoffLimit": 0, "template": template}}
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": ctx.metadata(name, labels),
        "spec": {
            "replicas": 1,
            # One incarnation at a time: a second one would register the same id while the first still runs.
            "strategy": {"type": "Recreate"},
            "revisionHistoryLimit": 3,
            "selector": {"matchLabels": ctx.selector(name)},
            "template": template,
        },
    }
