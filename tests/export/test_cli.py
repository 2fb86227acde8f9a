"""cast export as a person uses it: what it says, exporting again into the same directory (the secret kept, stale
files gone), and never writing over a directory it did not write."""

from __future__ import annotations

import textwrap
from pathlib import Path

from tests.conftest import ROOT
from tests.export.helpers import FULL, cast, checkout, objects


def test_exporting_the_demo_says_what_was_written_and_what_to_do_next(tmp_path: Path) -> None:
    out = tmp_path / "k8s"
    result = cast(ROOT, "export", "configs/demo.yaml", "--to", "kubernetes", "-o", str(out))
    assert result.code == 0 and result.err == ""
    assert result.out.startswith(f"cast export: configs/demo.yaml -> {out}/ (kubernetes): 9 files\n")
    assert "namespace scene-description; the directory (what components dial): server-main:7000" in result.out
    assert "secrets.yaml: the system secret (new); mode 0600: keep it out of version control" in result.out
    assert f"then: kubectl apply -k {out}" in result.out


def test_exporting_again_keeps_the_secret_and_removes_what_is_gone(tmp_path: Path) -> None:
    checkout(tmp_path)
    assert cast(tmp_path, "export", "system.yaml", "--to", "kubernetes", "-o", "out").code == 0
    first = next(o for o in objects(tmp_path / "out") if o["metadata"]["name"] == "cast-secret")
    assert (tmp_path / "out" / "mover.yaml").exists()
    (tmp_path / "system.yaml").write_text(textwrap.dedent(FULL).replace(
        'mover: {class: "tiny:Writer", restart: always}', "{}"))
    again = cast(tmp_path, "export", "system.yaml", "--to", "kubernetes", "-o", "out")
    assert again.code == 0, again.err
    assert "the system secret (kept from the previous export (out/secrets.yaml))" in again.out
    second = next(o for o in objects(tmp_path / "out") if o["metadata"]["name"] == "cast-secret")
    assert second["data"] == first["data"]
    assert not (tmp_path / "out" / "mover.yaml").exists()  # the component left the configuration


def test_a_directory_the_export_did_not_write_is_refused_and_left_alone(tmp_path: Path) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("mine")
    result = cast(ROOT, "export", "configs/minimal.yaml", "--to", "kubernetes", "-o", str(tmp_path / "out"))
    assert result.code == 2
    assert f"{tmp_path / 'out'} is not empty (notes.txt) and holds no earlier export (.cast-export)" in result.err
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["notes.txt"]


def test_a_too_short_secret_is_refused_naming_where_it_came_from(tmp_path: Path) -> None:
    (tmp_path / "short").write_text("tiny\n")
    result = cast(ROOT, "export", "configs/minimal.yaml", "--to", "kubernetes", "-o", str(tmp_path / "out"),
                  "--secret-file", str(tmp_path / "short"))
    assert result.code == 2
    assert f"the system secret from {tmp_path / 'short'}: the token secret is 4 bytes, shorter than 32" in result.err
    assert not (tmp_path / "out").exists()


def test_validate_checks_against_the_versions_asked_and_refuses_what_does_not_fit(tmp_path: Path) -> None:
    ok = cast(ROOT, "export", "configs/demo.yaml", "--to", "kubernetes", "-o", str(tmp_path / "ok"),
              "--validate", "1.30", "--validate", "v1.37.2")
    assert ok.code == 0, ok.err
    assert "valid for Kubernetes 1.30: 9 objects (kubernetes-validate, strict)" in ok.out
    checkout(tmp_path / "co")  # token_ttl: a native sidecar, which Kubernetes 1.27 does not have
    old = cast(tmp_path / "co", "export", "system.yaml", "--to", "kubernetes", "-o", "out", "--validate", "1.27")
    assert old.code == 2
    assert ("Deployment writer-1: at spec.template.spec.initContainers.1: Additional properties are not allowed "
            "('restartPolicy' was unexpected) (the token-renewing sidecar") in old.err
    assert "not valid for Kubernetes 1.27 (above); nothing was written" in old.err
    assert not (tmp_path / "co" / "out").exists()
    unknown = cast(ROOT, "export", "configs/demo.yaml", "--to", "kubernetes", "-o", str(tmp_path / "x"),
                   "--validate", "1.9")
    assert unknown.code == 2 and "--validate 1.9: give a Kubernetes version" in unknown.err and "1.37" in unknown.err


def test_the_pages_export_output_is_what_cast_export_prints(tmp_path: Path) -> None:
    page = (ROOT / "docs" / "deploy.md").read_text()
    start = page.index("$ cast export configs/demo.yaml --to kubernetes -o /tmp/k8s\n")
    shown = page[start:page.index("```", start)].splitlines()[1:]
    result = cast(ROOT, "export", "configs/demo.yaml", "--to", "kubernetes", "-o", str(tmp_path / "k8s"))
    assert result.out.replace(str(tmp_path / "k8s"), "/tmp/k8s").splitlines() == shown


def test_the_readmes_export_commands_run_as_written(tmp_path: Path) -> None:
    readme = (ROOT / "README.md").read_text()
    start = readme.index("## On a cluster engine: `cast export`\n")
    block = readme[readme.index("```sh\n", start) + 6:readme.index("```", readme.index("```sh\n", start) + 6)]
    commands = [line.split("#")[0].split() for line in block.splitlines() if line.startswith("cast ")]
    assert len(commands) == 3
    for argv in commands:
        argv = [str(tmp_path / w.removeprefix("/tmp/")) if w.startswith("/tmp/") else w for w in argv]
        result = cast(ROOT, *argv[1:])
        assert result.code == 0, (argv, result.err)
    assert (tmp_path / "k8s" / "kustomization.yaml").exists()
    assert (tmp_path / "units" / "robot" / "cast-agent.service").exists()
