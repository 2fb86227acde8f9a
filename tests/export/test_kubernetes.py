"""cast export --to kubernetes: every manifest is valid for two Kubernetes versions (kubernetes-validate's bundled
schemas, offline), and the manifests read back keep the invariants that matter: the secret stays out of component
containers, every address resolves to a Service of the export, durable servers have a volume, probes use gRPC
health, and the configuration maps as docs/deploy.md says."""

from __future__ import annotations

import base64
import stat
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest

from tests.conftest import ROOT
from tests.export.helpers import cast, checkout, documents, objects, pod_spec, workloads

# Two recent versions kubernetes-validate ships (native sidecars, used for renewing tokens, need 1.29 or newer).
VERSIONS = ("1.30", "1.37")
SHIPPED = ["configs/demo.yaml", "configs/demo-multihost.yaml", "configs/minimal.yaml", "configs/pipeline.yaml",
           "configs/experiments/decomposition.yaml", "examples/quickstart/system.yaml", "examples/java/system.yaml",
           "examples/cpp/hello/system.yaml"]


@pytest.fixture(scope="module")
def full(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The export of the configuration that uses every feature (tests/export/helpers.py: FULL)."""
    root = tmp_path_factory.mktemp("checkout")
    checkout(root)
    result = cast(root, "export", "system.yaml", "--to", "kubernetes", "-o", "out")
    assert result.code == 0, result.err
    return root / "out"


def _validate(out_dir: Path) -> int:
    count = 0
    for obj in objects(out_dir):
        for version in VERSIONS:
            try:
                kubernetes_validate.validate(obj, version, strict=True)
            except kubernetes_validate.ValidationError as exc:
                where = "/".join(str(p) for p in exc.absolute_path)
                raise AssertionError(f"{obj['kind']} {obj['metadata']['name']} is invalid for Kubernetes {version} "
                                     f"at {where}: {exc.message}") from None
        count += 1
    return count


@pytest.mark.parametrize("config", SHIPPED)
def test_every_manifest_of_a_shipped_configuration_is_valid_for_two_kubernetes_versions(tmp_path: Path,
                                                                                       config: str) -> None:
    result = cast(ROOT, "export", config, "--to", "kubernetes", "-o", str(tmp_path / "out"))
    assert result.code == 0, result.err
    assert _validate(tmp_path / "out") >= 3  # namespace, secret, a server's Service and workload at least


def test_every_manifest_of_the_full_configuration_is_valid_for_two_kubernetes_versions(full: Path) -> None:
    assert _validate(full) == 1 + 3 + 2 * 2 + 7  # namespace, 3 secrets, 2 servers x 2, 7 launched components


def test_the_validation_catches_a_wrong_manifest(full: Path) -> None:
    deployment = workloads(full)["writer-1"]
    deployment["spec"]["template"]["spec"]["containers"][0]["volumeMount"] = []  # a misspelt key
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(deployment, VERSIONS[0], strict=True)


def test_the_kustomization_lists_every_file_and_sets_the_namespace(full: Path) -> None:
    docs = documents(full)
    (kustomization,) = docs.pop("kustomization.yaml")
    assert kustomization["kind"] == "Kustomization" and kustomization["namespace"] == "robot-system-1"
    assert sorted(kustomization["resources"]) == sorted(docs)
    assert {o["metadata"].get("namespace") for o in objects(full) if o["kind"] != "Namespace"} == {"robot-system-1"}


# -------------------------------------------------------------------------------- the secret

def _secret_names(pod: dict[str, Any], volume_mounts: list[dict[str, Any]]) -> set[str]:
    """The Secrets a container mounts (through the pod's volumes)."""
    by_volume = {v["name"]: v["secret"]["secretName"] for v in pod.get("volumes", []) if "secret" in v}
    return {by_volume[m["name"]] for m in volume_mounts if m["name"] in by_volume}


def _containers(pod: dict[str, Any]) -> list[dict[str, Any]]:
    return [*pod.get("initContainers", []), *pod["containers"]]


def test_no_component_container_mounts_the_system_secret_only_token_containers_and_servers_do(full: Path) -> None:
    mounting: dict[str, set[str]] = {}
    for name, workload in workloads(full).items():
        pod = pod_spec(workload)
        for container in _containers(pod):
            secrets = _secret_names(pod, container.get("volumeMounts", []))
            assert "envFrom" not in container
            assert not [e for e in container.get("env", []) if "valueFrom" in e], (name, container["name"])
            if "cast-secret" in secrets:
                mounting.setdefault(container["name"], set()).add(name)
            if container["name"] == "component":
                assert secrets <= {"cast-tls-client"}, (name, secrets)  # never the secret, never a server's key
    assert set(mounting) == {"token", "token-renewer", "server"}
    assert mounting["server"] == {"server-main", "server-far"}
    assert mounting["token"] == mounting["token-renewer"] == {"writer-1", "watcher", "once", "seg", "col", "node-1",
                                                               "mover"}


def test_the_secret_file_is_private_and_holds_the_secret_given(tmp_path: Path) -> None:
    checkout(tmp_path)
    (tmp_path / "my-secret").write_text("the-system-secret-of-at-least-32-bytes\n")
    result = cast(tmp_path, "export", "system.yaml", "--to", "kubernetes", "-o", "out", "--secret-file", "my-secret")
    assert result.code == 0, result.err
    assert stat.S_IMODE((tmp_path / "out" / "secrets.yaml").stat().st_mode) == 0o600
    secret = next(o for o in objects(tmp_path / "out") if o["metadata"]["name"] == "cast-secret")
    assert base64.b64decode(secret["data"]["secret"]) == b"the-system-secret-of-at-least-32-bytes"
    server_key = next(o for o in objects(tmp_path / "out") if o["metadata"]["name"] == "cast-tls-server")
    assert base64.b64decode(server_key["data"]["key"]) == b"contents of certs/server.key\n"
    client = next(o for o in objects(tmp_path / "out") if o["metadata"]["name"] == "cast-tls-client")
    assert set(client["data"]) == {"ca", "cert", "key"}
    assert base64.b64decode(client["data"]["key"]) == b"contents of certs/client.key\n"  # not the server's key


# ------------------------------------------------------------------------------- addresses

def _services(out_dir: Path) -> dict[str, set[int]]:
    return {o["metadata"]["name"]: {p["port"] for p in o["spec"]["ports"]} for o in objects(out_dir)
            if o["kind"] == "Service"}


def _resolves(address: str, services: dict[str, set[int]]) -> bool:
    host, _, port = address.rpartition(":")
    return int(port) in services.get(host, set())


@pytest.mark.parametrize("config", ["full", "configs/demo.yaml"])
def test_every_address_a_container_dials_is_a_service_of_the_same_export(full: Path, tmp_path: Path,
                                                                          config: str) -> None:
    out = full
    if config != "full":
        out = tmp_path / "out"
        assert cast(ROOT, "export", config, "--to", "kubernetes", "-o", str(out)).code == 0
    services = _services(out)
    dialled = []
    for workload in workloads(out).values():
        for container in _containers(pod_spec(workload)):
            env = {e["name"]: e["value"] for e in container.get("env", [])}
            argv = container["command"]
            dialled += [env["CAST_ENDPOINT"]] if "CAST_ENDPOINT" in env else []
            dialled += [argv[i + 1] for i, word in enumerate(argv) if word == "--endpoint"]
            dialled += [argv[i + 1].partition("=")[2] for i, word in enumerate(argv) if word == "--route"]
    assert dialled and all(_resolves(a, services) for a in dialled), (dialled, services)
    # Each server's Service selects that server's pods, on the port its container listens on.
    for name, ports in services.items():
        container = pod_spec(workloads(out)[name])["containers"][0]
        assert {p["containerPort"] for p in container["ports"]} == ports
        assert f"0.0.0.0:{next(iter(ports))}" in container["command"]


def test_the_servers_listen_on_their_configured_port_or_7000_and_know_each_others_sas(full: Path) -> None:
    assert _services(full) == {"server-main": {7000}, "server-far": {7100}}
    main = pod_spec(workloads(full)["server-main"])["containers"][0]["command"]
    far = pod_spec(workloads(full)["server-far"])["containers"][0]["command"]
    assert main[:3] == ["cast", "serve", "/opt/cast/system.yaml"] and "--server" in main and "main" in main
    assert "motor=server-far:7100" in main and {"vision=server-main:7000", "language=server-main:7000"} <= set(far)
    assert "SPEED=3" in main and main[main.index("--lease-ms") + 1] == "4000"


# ------------------------------------------------------------------------ volumes and probes

def test_every_durable_server_has_a_volume_where_its_journal_is(full: Path) -> None:
    far, main = workloads(full)["server-far"], workloads(full)["server-main"]
    assert far["kind"] == "StatefulSet" and main["kind"] == "Deployment"
    (claim,) = far["spec"]["volumeClaimTemplates"]
    assert claim["spec"]["accessModes"] == ["ReadWriteOnce"] and claim["spec"]["resources"]["requests"]["storage"]
    mounts = {m["name"]: m["mountPath"] for m in pod_spec(far)["containers"][0]["volumeMounts"]}
    assert mounts["journal"] == "/opt/cast/data/far"  # data/far/journal.sqlite, in the image's checkout
    assert far["spec"]["serviceName"] == "server-far"


def test_server_probes_ask_the_grpc_health_service(full: Path, tmp_path: Path) -> None:
    assert cast(ROOT, "export", "configs/demo.yaml", "--to", "kubernetes", "-o", str(tmp_path / "demo")).code == 0
    plain = pod_spec(workloads(tmp_path / "demo")["server-main"])["containers"][0]
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert plain[probe]["grpc"] == {"port": 7000}, probe
        tls = pod_spec(workloads(full)["server-far"])["containers"][0][probe]["exec"]["command"]
        # kubelet's grpc probe has no TLS: the health service is asked over TLS from inside the container.
        assert tls[:3] == ["python", "-m", "cast.export.health_probe"] and tls[3] == "127.0.0.1:7100"
        assert tls[tls.index("--server-name") + 1] == "server-far"
        assert {"--ca", "--cert", "--key"} <= set(tls)


# ----------------------------------------------------------------------- how components map

def test_restart_policies_map_to_deployments_and_a_job(full: Path) -> None:
    found = workloads(full)
    assert found["once"]["kind"] == "Job"
    assert found["once"]["spec"]["backoffLimit"] == 0 and pod_spec(found["once"])["restartPolicy"] == "Never"
    for name in ("writer-1", "mover", "seg"):
        assert found[name]["kind"] == "Deployment" and found[name]["spec"]["strategy"] == {"type": "Recreate"}
        assert "restartPolicy" not in pod_spec(found[name])  # Always, a Deployment's only policy
    assert {"inproc", "later"}.isdisjoint(found)  # in its server; started by hand
    assert all(pod_spec(w)["terminationGracePeriodSeconds"] == 7 for w in found.values())


def test_the_launch_contract_is_in_each_component_containers_environment(full: Path) -> None:
    pod = pod_spec(workloads(full)["writer-1"])
    container = pod["containers"][0]
    env = {e["name"]: e["value"] for e in container["env"]}
    assert env["CAST_COMPONENT_ID"] == "Writer_1" and env["CAST_SUBARCHITECTURE"] == "vision"
    assert env["CAST_ARGS"] == '{"speed": 3}' and env["PYTHONPATH"] == "/opt/cast/components"
    assert env["CAST_ENDPOINT"] == "server-main:7000" and "CAST_TOKEN" not in env
    assert {env["CAST_TLS_CA"], env["CAST_TLS_CERT"], env["CAST_TLS_KEY"]} == {
        "/var/run/cast/tls/ca", "/var/run/cast/tls/cert", "/var/run/cast/tls/key"}
    # The runner itself, no shell line: it reads the token from CAST_TOKEN_FILE, never from its environment.
    assert container["command"] == ["python", "-m", "cast.run", "tiny:Writer"]
    token, renewer = pod["initContainers"]
    assert env["CAST_TOKEN_FILE"] == token["command"][token["command"].index("--write") + 1]
    assert token["command"][:3] == ["cast", "token", "Writer_1"] and "--renew" not in token["command"]
    assert renewer["restartPolicy"] == "Always" and renewer["command"][-1] == "--renew"
    assert token["command"][token["command"].index("--ttl") + 1] == "6"
    watcher = pod_spec(workloads(full)["watcher"])
    assert "--privileged" in watcher["initContainers"][0]["command"]
    assert watcher["nodeSelector"] == {"cast/host": "arm"}


def test_each_language_runs_in_its_image_with_the_checkouts_paths_under_opt_cast(full: Path) -> None:
    found = {name: pod_spec(w)["containers"][0] for name, w in workloads(full).items()}
    assert found["seg"]["image"] == "cast-cpp:0.1.0" and found["seg"]["command"] == ["/opt/cast/bin/seg"]
    assert found["col"]["image"] == "cast-java:0.1.0"
    assert found["col"]["command"] == ["java", "-cp", "/opt/cast/java_client/target/cast-client-all.jar:/opt/cast/"
                                       "jars/x.jar", "cast.client.Runner", "a.B"]
    assert found["node-1"]["image"] == "registry.example:5000/robot/node-comp:1"
    assert found["node-1"]["command"] == ["node", "comp.js"] and found["node-1"]["workingDir"] == "/opt/cast"
    components = [c for w in workloads(full).values() for c in pod_spec(w)["containers"] if c["name"] == "component"]
    assert len(components) == 7
    for container in components:  # no shell in between, no token in the environment: CAST_TOKEN_FILE only
        assert not {"sh", "/bin/sh", "bash", "-c"} & set(container["command"]), container["command"]
        names = {e["name"] for e in container["env"]}
        assert "CAST_TOKEN_FILE" in names and "CAST_TOKEN" not in names, names
    python = "registry.example:5000/robot/cast-python:0.1.0"
    assert found["writer-1"]["image"] == found["server-main"]["image"] == python
    assert all(c["image"] == python for w in workloads(full).values() for c in pod_spec(w).get("initContainers", []))
    assert {c["imagePullPolicy"] for w in workloads(full).values() for c in _containers(pod_spec(w))} == {"Always"}


def test_every_container_runs_unprivileged_on_a_read_only_root(full: Path) -> None:
    for name, workload in workloads(full).items():
        pod = pod_spec(workload)
        assert pod["securityContext"]["runAsNonRoot"] is True and pod["automountServiceAccountToken"] is False, name
        for container in _containers(pod):
            security = container["securityContext"]
            assert security["allowPrivilegeEscalation"] is False and security["readOnlyRootFilesystem"] is True
            assert any(m["mountPath"] == "/tmp" for m in container["volumeMounts"]), (name, container["name"])
