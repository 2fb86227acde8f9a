"""Configuration: valid files pass; every class of mistake is reported with its file, line and key."""

from __future__ import annotations

import subprocess
import textwrap
from pathlib import Path

import pytest

from cast.config import ConfigError, Problem, load_config, parse_config, read_config
from cast.orchestrator.preflight import preflight
from tests.conftest import ROOT
from tests.orchestrator.conftest import CAST, COMPONENTS

GOOD = f"""\
system: good
python_path: [{COMPONENTS}]
subarchitectures:
  vision:
    task_manager: {{policy: fifo, max_concurrent: 2}}
    components:
      producer: {{language: python, kind: unmanaged, class: orch_components:Producer, args: {{count: 2}}}}
      worker: {{language: python, kind: managed, class: orch_components:Worker}}
  language:
    task_manager: {{policy: exclusive}}
"""


def problems(tmp_path: Path, text: str, deep: bool = False, **others: str) -> list[Problem]:
    for name, body in others.items():
        (tmp_path / name.replace("__", ".")).write_text(textwrap.dedent(body))
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent(text))
    config, found = read_config(path, environ={})
    if deep and config is not None and not found.errors:
        preflight(config, found)
    return found.items


def one(found: list[Problem], line: int, key: str, text: str, file: str = "system.yaml") -> Problem:
    """The problem at ``line`` whose key and message contain ``key`` and ``text``."""
    hits = [p for p in found if p.position.line == line and key in p.key and text in p.message
            and p.position.file.endswith(file)]
    assert hits, f"no problem at {file}:{line} with key {key!r} and {text!r}; got:\n" + "\n".join(map(str, found))
    return hits[0]


# ------------------------------------------------------------------- valid files

@pytest.mark.parametrize("name", ["demo.yaml", "minimal.yaml"])
def test_shipped_configurations_pass_cast_check(demo_built: Path, name: str) -> None:
    out = subprocess.run([CAST, "check", str(ROOT / "configs" / name)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert ": ok: system" in out.stdout


def test_demo_language_choices_are_valid_files(demo_built: Path) -> None:
    # The C++ and Java choices (the defaults) only warn while those builds are missing; the files are valid.
    for sets in (["SEGMENTER_LANGUAGE=cpp"], ["COLOUR_LANGUAGE=java"], ["SEGMENTER_LANGUAGE=python"],
                 ["COLOUR_LANGUAGE=python"]):
        config, found = read_config(demo_built, dict(s.split("=") for s in sets))
        assert config is not None and not found.errors, [str(p) for p in found.items]


def test_a_good_file_gives_the_model(tmp_path: Path) -> None:
    path = tmp_path / "good.yaml"
    path.write_text(GOOD)
    config = load_config(path, environ={})
    assert config.name == "good"
    assert list(config.subarchitectures) == ["vision", "language"]
    assert [c.id for c in config.components] == ["producer", "worker"]
    worker = config.component("worker")
    assert worker is not None and worker.kind == "managed" and worker.subarchitecture == "vision"
    assert config.component("producer").args == {"count": 2}  # type: ignore[union-attr]
    assert config.subarchitectures["vision"].make_policy().describe() == "fifo(max_concurrent=2)"
    assert [(s.name, s.subarchitectures) for s in config.servers] == [("main", ["vision", "language"])]
    found: list[Problem] = []
    problems_obj = read_config(path, environ={})[1]
    preflight(config, problems_obj)
    found = problems_obj.items
    assert found == []


def test_parse_config_accepts_plain_data() -> None:
    config = parse_config({"system": "x", "subarchitectures": {"a": {}, "b": {"task_manager": {"policy": "always"}}}})
    assert list(config.subarchitectures) == ["a", "b"]


# ---------------------------------------------------------------- each mistake

def test_yaml_syntax_error_names_its_line(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        system: broken
        subarchitectures:
          vision:
            components: {segmenter: {class: a:B}
          language: {}
        """)
    assert len(found) == 1
    assert "invalid YAML" in found[0].message
    assert found[0].position.line == 5


def test_unknown_key_with_suggestion(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        system: typo
        subarchitecture:
          vision: {}
        """)
    one(found, 2, "subarchitecture", "did you mean 'subarchitectures'?")


def test_misspelt_component_and_policy_keys(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision:
            task_manager: {policy: fifo, max_concurent: 2}
            components:
              seg:
                langauge: python
                class: a:B
        """)
    one(found, 3, "max_concurent", "did you mean 'max_concurrent'?")
    one(found, 6, "langauge", "did you mean 'language'?")


def test_missing_class(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision:
            components:
              seg: {language: python, kind: unmanaged}
              rec: {language: java, kind: managed}
        """)
    one(found, 4, "seg.class", "needs 'class: module:Class'")
    one(found, 5, "rec.class", "fully.qualified.ClassName")


def test_class_that_does_not_import_or_is_no_component(tmp_path: Path) -> None:
    found = problems(tmp_path, f"""\
        python_path: [{COMPONENTS}]
        subarchitectures:
          vision:
            components:
              a: {{class: no_such_module:Thing}}
              b: {{class: orch_components:NoSuchClass}}
              c: {{class: orch_policies:PrefixPolicy}}
              d: {{class: orch_components:Worker, kind: unmanaged}}
        """, deep=True)
    one(found, 5, "a.class", "cannot import module 'no_such_module'")
    one(found, 6, "b.class", "is not a component class")
    one(found, 7, "c.class", "is not a component class")
    one(found, 8, "d.kind", "is a managed component but the configuration says kind: unmanaged")


def test_unknown_subarchitecture(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision: {}
        components:
          mover:
            subarchitecture: visoin
            class: a:B
        servers:
          main:
            subarchitectures: [vision, motor]
        """)
    one(found, 5, "mover.subarchitecture", "unknown subarchitecture 'visoin' (did you mean 'vision'?)")
    one(found, 9, "servers.main.subarchitectures", "unknown subarchitecture 'motor'")


def test_duplicate_component_id(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision:
            components:
              seg: {class: a:B}
          language:
            components:
              seg: {class: a:C}
        """)
    p = one(found, 7, "seg", "component id 'seg' is used twice")
    assert "system.yaml:4" in p.message  # where the first one is


def test_duplicate_key_in_one_mapping(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision:
            components:
              seg: {class: a:B}
              seg: {class: a:C}
        """)
    one(found, 5, "seg", "given twice (first at line 4)")


def test_bad_policy(tmp_path: Path) -> None:
    found = problems(tmp_path, f"""\
        python_path: [{COMPONENTS}]
        subarchitectures:
          a:
            task_manager: {{policy: fido}}
          b:
            task_manager: {{policy: fifo, max_concurrent: -1}}
          c:
            task_manager: {{policy: "orch_policies:Missing"}}
          d:
            task_manager: {{policy: "orch_components:Worker"}}
        """)
    one(found, 4, "a.task_manager.policy", "unknown task manager policy 'fido' (did you mean 'fifo'?)")
    one(found, 6, "b.task_manager", "max_concurrent must be a whole number >= 0")
    one(found, 8, "c.task_manager.policy", "cannot be loaded")
    one(found, 10, "d.task_manager.policy", "is not a subclass of cast.TaskPolicy")


def test_bad_values(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision:
            components:
              a: {language: rust, class: a:B}
              b: {class: a:B, restart: sometimes}
              c: {class: a:B, privileged: maybe}
              d: {language: cpp, in_process: true, run: x}
              e: {class: a:B, restart: {policy: always, max_restarts: -2}}
              "bad id": {class: a:B}
        servers:
          main: {listen: nowhere, subarchitectures: [vision]}
        """)
    one(found, 4, "a.language", "'rust' is not one of python, cpp, java")
    one(found, 5, "b.restart", "'sometimes' is not one of never, on-failure, always")
    one(found, 6, "c.privileged", "must be true or false")
    one(found, 7, "d.in_process", "only python components can run in process")
    one(found, 8, "e.restart.max_restarts", "must be a whole number >= 0")
    one(found, 9, "bad id", "component id 'bad id' must be")
    one(found, 11, "servers.main.listen", "must be HOST:PORT")


def test_tls_client_certificate_needs_its_key(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures: {vision: {}}
        tls: {ca: ca.pem, cert: s.pem, key: s.key, client_auth: true, client_cert: c.pem}
        """)
    one(found, 2, "tls.client_key", "give client_cert and client_key together")
    config, _ = read_config(_write(tmp_path / "ok.yaml", """\
        subarchitectures: {vision: {}}
        tls: {ca: ca.pem, cert: s.pem, key: s.key, client_auth: true, client_cert: c.pem, client_key: c.key}
        """), environ={})
    assert config is not None and config.tls is not None
    assert config.tls.component_identity == (tmp_path / "c.pem", tmp_path / "c.key")


def _write(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


def test_every_problem_is_reported_not_just_the_first(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(
        "subarchitectures:\n  v:\n    task_manager: {policy: nope}\n    componets: {}\nlimits: {max_entries: 0}\n"
    )
    with pytest.raises(ConfigError) as info:
        load_config(path, environ={})
    lines = str(info.value).splitlines()
    assert len([p for p in info.value.problems if not p.warning]) == 3
    assert lines[-1] == "configuration has 3 errors"
    assert all(line.startswith(f"{path}:") for line in lines[:-1])


def test_cast_check_exit_codes_and_output(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("subarchitectures:\n  vision:\n    components:\n      x: {clas: a:B}\n")
    out = subprocess.run([CAST, "check", str(bad)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert f"{bad}:4: error: subarchitectures.vision.components.x.clas: unknown key 'clas' (did you mean 'class'?)" \
        in out.stderr
    good = tmp_path / "good.yaml"
    good.write_text(GOOD)
    out = subprocess.run([CAST, "check", str(good)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "2 subarchitectures, 2 components (2 python)" in out.stdout


def test_missing_cpp_build_warns_in_check_but_fails_run(tmp_path: Path) -> None:
    cfg = tmp_path / "cpp.yaml"
    cfg.write_text("subarchitectures:\n  vision:\n    components:\n      seg: {language: cpp, run: no-such-binary}\n")
    env = {"CAST_CPP_BIN_DIR": str(tmp_path / "bin"), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([CAST, "check", str(cfg)], capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr
    assert f"{cfg}:4: warning: components.seg.run: executable 'no-such-binary' is not in" in out.stderr
    assert "1 subarchitecture, 1 component (1 cpp)" in out.stdout  # one of each: no plural
    out = subprocess.run([CAST, "run", str(cfg), "--for", "1", "--runtime-dir", str(tmp_path / "rt")],
                         capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 2
    assert "error: components.seg.run" in out.stderr and "nothing was started" in out.stderr


# ------------------------------------------------------------ variables, includes

def test_variables_from_set_environment_file_and_default(tmp_path: Path) -> None:
    path = tmp_path / "vars.yaml"
    path.write_text(textwrap.dedent("""\
        system: ${NAME:-fallback}
        variables: {N: 3, SA: from-file}
        subarchitectures:
          ${SA}:
            task_manager: {policy: fifo, max_concurrent: "${N}"}
            components:
              p:
                class: a:B
                args:
                  n: ${N}
                  quoted: "${N}"
                  text: "n=${N}"
                  literal: "$${N}"
        """))
    config = load_config(path, environ={})
    assert config.name == "fallback"
    assert list(config.subarchitectures) == ["from-file"]
    assert config.components[0].args == {"n": 3, "quoted": 3, "text": "n=3", "literal": "${N}"}
    config = load_config(path, environ={"SA": "from-env", "NAME": "env"})
    assert (config.name, list(config.subarchitectures)) == ("env", ["from-env"])
    config = load_config(path, {"SA": "from-set", "N": "5"}, environ={"SA": "from-env"})
    assert list(config.subarchitectures) == ["from-set"]
    assert config.components[0].args["n"] == 5
    assert config.variables == {"NAME": "fallback", "SA": "from-set", "N": "5"}


def test_unset_variable_is_an_error_on_its_line(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision:
            components:
              p: {class: "${CLASS}"}
        """)
    one(found, 4, "p.class", "variable 'CLASS' is not set")


def test_includes_merge_relative_to_the_including_file(tmp_path: Path) -> None:
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "vision.yaml").write_text(textwrap.dedent("""\
        variables: {RATE: 7}
        subarchitectures:
          vision:
            task_manager: {policy: fifo}
            components:
              seg: {class: a:Seg, args: {rate: "${RATE}"}}
        """))
    (tmp_path / "parts" / "extra-on.yaml").write_text("subarchitectures:\n  extra: {}\n")
    path = tmp_path / "top.yaml"
    path.write_text(textwrap.dedent("""\
        system: merged
        include: [parts/vision.yaml, "parts/extra-${EXTRA:-on}.yaml"]
        subarchitectures:
          vision:
            task_manager: {policy: exclusive}
            components:
              rec: {class: a:Rec}
        """))
    config = load_config(path, environ={})
    assert list(config.subarchitectures) == ["vision", "extra"]
    vision = config.subarchitectures["vision"]
    assert vision.policy == "exclusive"  # the including file wins
    assert list(vision.components) == ["seg", "rec"]
    assert vision.components["seg"].args == {"rate": 7}
    assert vision.components["seg"].position.file.endswith("parts/vision.yaml")
    found = problems(tmp_path, "include: parts/missing.yaml\nsubarchitectures: {a: {}}\n")
    one(found, 1, "include", "cannot read")


def test_include_cycle_and_errors_inside_included_files(tmp_path: Path) -> None:
    found = problems(tmp_path, "include: [a.yaml]\nsubarchitectures: {x: {}}\n",
                     a__yaml="include: [system.yaml]\n",)
    one(found, 1, "include", "include each other in a cycle", file="a.yaml")
    found = problems(tmp_path, "include: [b.yaml]\nsubarchitectures: {x: {}}\n",
                     b__yaml="subarchitectures:\n  x:\n    componentz: {}\n")
    one(found, 3, "componentz", "did you mean 'components'?", file="b.yaml")


def test_servers_map_subarchitectures(tmp_path: Path) -> None:
    path = tmp_path / "servers.yaml"
    path.write_text(textwrap.dedent("""\
        subarchitectures: {vision: {}, language: {}, motor: {}}
        servers:
          main: {listen: "127.0.0.1:0", subarchitectures: [vision, language]}
          motor: {subarchitectures: [motor]}
        """))
    config = load_config(path, environ={})
    assert [(s.name, s.listen, s.subarchitectures) for s in config.servers] == [
        ("main", "127.0.0.1:0", ["vision", "language"]), ("motor", "127.0.0.1:0", ["motor"])]
    found = problems(tmp_path, textwrap.dedent("""\
        subarchitectures: {vision: {}, motor: {}}
        servers:
          a: {subarchitectures: [vision]}
          b: {subarchitectures: [vision]}
        """))
    one(found, 4, "servers.b.subarchitectures", "already hosted by server 'a'")
    one(found, 2, "servers", "no server hosts subarchitecture 'motor'")


def test_component_quotas_reach_the_server(tmp_path: Path) -> None:
    from cast.core.records import Identity, Quota
    from cast.errors import ResourceExhaustedError
    from cast.server.app import system_from_config

    path = _write(tmp_path / "system.yaml", """\
        subarchitectures:
          v:
            components:
              small: {class: "m:C", quota: {entries: 1, bytes: 100}}
              free: {class: "m:C"}
        """)
    config = load_config(path, environ={})
    assert config.subarchitectures["v"].components["small"].quota == Quota(1, 100)
    system = system_from_config(config)
    system.host.add(Identity("small", "v"), "v", "a", "t.T", b"")
    with pytest.raises(ResourceExhaustedError, match="components.small.quota"):
        system.host.add(Identity("small", "v"), "v", "b", "t.T", b"")
    system.host.add(Identity("free", "v"), "v", "b", "t.T", b"x" * 1000)
    found = problems(tmp_path, "subarchitectures:\n  v:\n    components:\n      c: {class: 'm:C', quota: {entries: -1, "
                               "byts: 3}}\n")
    assert {p.key for p in found} == {"subarchitectures.v.components.c.quota.entries",
                                      "subarchitectures.v.components.c.quota.byts"}, found


# ------------------------------------------------------------------- hosts
