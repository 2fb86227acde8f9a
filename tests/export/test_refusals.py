"""What an engine cannot express is refused by `cast check --to ENGINE` and `cast export --to ENGINE` alike, each
on its line with what to change, and nothing is written; a wrong images: section is refused by every cast check."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.export.helpers import cast, checkout

# Line numbers below are those of this text (after dedent), from 1.
REFUSED = """\
    system: refused
    include: [../outside.yaml]
    python_path: [components, /elsewhere/lib]
    persistence: {path: journal.sqlite}
    subarchitectures:
      vision:
        components:
          node: {language: other, run: "node comp.js"}
          col: {language: java, class: a.B, classpath: [/elsewhere/x.jar]}
          seg: {language: cpp, run: ../build/seg}
          Cam_1: {class: "m:A"}
          cam.1: {class: "m:A"}
          a_component_whose_id_is_much_too_long_for_a_kubernetes_name: {class: "m:A"}
          py: {class: "m:A"}
    """
EXPECTED = [  # (line, key, words of the message)
    (3, "python_path", "/elsewhere/lib (a directory of python_path) is outside the checkout"),
    (4, "persistence.path", "would hide what else is there (the checkout itself)"),
    (8, "components.node.language", "images: {components: {node: IMAGE}}"),
    (9, "components.col.classpath", "/elsewhere/x.jar (on the class path of component 'col') is outside"),
    (10, "components.seg.run", "build/seg (the executable of component 'seg') is outside the checkout"),
    (12, "components.cam.1", "becomes the Kubernetes name 'cam-1', which component 'Cam_1' (line 11) has"),
    (13, "components.a_component", "has 1 to 52"),
]


@pytest.fixture
def refused(tmp_path: Path) -> Path:
    root = tmp_path / "checkout"
    checkout(root, REFUSED, files=())
    (root / "components").mkdir()
    (root / "components" / "m.py").write_text("import cast\n\n\nclass A(cast.UnmanagedComponent):\n    pass\n")
    (tmp_path / "outside.yaml").write_text("orchestrator: {stop_timeout: 3}\n")
    return root


def assert_refusals(err: str) -> None:
    for line, key, words in EXPECTED:
        hits = [e for e in err.splitlines() if e.startswith(f"system.yaml:{line}: error: {key}") and words in e]
        assert hits, f"no error on line {line} for {key} saying {words!r} in:\n{err}"
    outside = [e for e in err.splitlines() if "outside.yaml" in e and "is outside the checkout" in e]
    assert outside, err


def test_cast_check_to_kubernetes_refuses_each_thing_on_its_line(refused: Path) -> None:
    plain = cast(refused, "check", "system.yaml")  # cast run could run it: only the engine refuses
    assert "error" not in plain.err
    result = cast(refused, "check", "system.yaml", "--to", "kubernetes")
    assert result.code == 1, result.err
    assert_refusals(result.err)
    assert len([e for e in result.err.splitlines() if ": error: " in e]) == len(EXPECTED) + 1


def test_cast_export_refuses_the_same_and_writes_nothing(refused: Path) -> None:
    result = cast(refused, "export", "system.yaml", "--to", "kubernetes", "-o", "out")
    assert result.code == 2
    assert_refusals(result.err)
    assert "system.yaml has 8 errors; nothing was written" in result.err
    assert not (refused / "out").exists()


def test_a_journal_in_a_directory_of_its_own_and_an_image_for_the_other_component_are_accepted(tmp_path: Path) -> None:
    checkout(tmp_path, """\
        persistence: {path: data/main/journal.sqlite}
        images: {components: {node: node-comp:1}}
        subarchitectures:
          v: {components: {node: {language: other, run: "node comp.js"}}}
        """, files=("data/main/journal.sqlite-wal",))
    result = cast(tmp_path, "check", "system.yaml", "--to", "kubernetes")
    assert result.code == 0, result.err
    assert "ok" in result.out


def test_systemd_refuses_a_configuration_outside_the_checkout(tmp_path: Path) -> None:
    config = checkout(tmp_path / "elsewhere", "subarchitectures: {v: {}}\n", files=())
    (tmp_path / "checkout").mkdir()
    result = cast(tmp_path / "checkout", "export", str(config), "--to", "systemd", "-o", "out")
    assert result.code == 2
    assert f"{config}: error: {config} is outside the checkout {tmp_path / 'checkout'}" in result.err
    assert "run the command from the checkout's root" in result.err
    assert not (tmp_path / "checkout" / "out").exists()


def test_a_tls_file_that_cannot_be_read_is_refused_on_its_line(tmp_path: Path) -> None:
    checkout(tmp_path, """\
        subarchitectures: {v: {}}
        tls:
          ca: ca.pem
          cert: server.pem
          key: missing.key
        """, files=("ca.pem", "server.pem"))
    result = cast(tmp_path, "export", "system.yaml", "--to", "kubernetes", "-o", "out")
    assert result.code == 2
    assert "system.yaml:5: error: tls.key: cannot read" in result.err and "missing.key" in result.err


def test_every_cast_check_refuses_an_image_for_an_in_process_or_unknown_component(tmp_path: Path) -> None:
    checkout(tmp_path, """\
        images:
          python: Not An Image
          pull_policy: Sometimes
          components:
            inproc: x:1
            writr: y:1
        subarchitectures:
          v:
            components:
              inproc: {class: "m:A", in_process: true}
              writer: {class: "m:A"}
        """, files=())
    result = cast(tmp_path, "check", "system.yaml")
    assert result.code == 1
    err = result.err
    assert "system.yaml:2: error: images.python: 'Not An Image' must be a container image" in err
    assert "system.yaml:3: error: images.pull_policy: 'Sometimes' is not one of IfNotPresent, Always, Never" in err
    assert ("system.yaml:5: error: images.components.inproc: component 'inproc' is in_process: it runs inside "
            "server 'main'") in err and "cannot have a container of its own" in err and "(line 10)" in err
    assert "system.yaml:6: error: images.components.writr: no component 'writr' in this system (did you mean " \
           "'writer'?)" in err


def test_bad_options_are_refused_before_anything_is_read(tmp_path: Path) -> None:
    for argv, words in (
        (["--to", "systemd", "--namespace", "x"], "--namespace is for --to kubernetes only"),
        (["--to", "kubernetes", "--user", "x"], "--user is for --to systemd only"),
        (["--to", "kubernetes", "--namespace", "Not_Valid"], "--namespace 'Not_Valid' is no Kubernetes namespace"),
        (["--to", "systemd", "--root", "relative"], "--root relative: give the checkout's absolute path"),
        (["--to", "kubernetes", "--volume-size", "lots"], "--volume-size 'lots': give a Kubernetes quantity"),
    ):
        result = cast(ROOT, "export", "configs/minimal.yaml", "-o", str(tmp_path / "out"), *argv)
        assert result.code == 2 and words in result.err, (argv, result.err)
        assert not (tmp_path / "out").exists()
