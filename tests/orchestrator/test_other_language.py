"""`language: other`: a component in any language, started from its `run:` command line with the launch contract."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

from google.protobuf.wrappers_pb2 import StringValue

from cast.config import load_config, read_config
from cast.core.records import Identity
from cast.orchestrator.launchers import LAUNCHERS
from cast.orchestrator.supervisor import Phase
from tests.orchestrator.conftest import CAST, COMPONENTS, Embedded, wait_for
from tests.orchestrator.test_config import one, problems

# A program that is not a CAST client at all: it records its launch (the contract's variables, its
# arguments and its working directory) in the file named by its first argument, prints a line, exits 0.
RECORDER = textwrap.dedent("""\
    import json, os, sys
    keys = [k for k in os.environ if k.startswith("CAST_")]
    record = {"env": {k: os.environ[k] for k in keys}, "argv": sys.argv[1:], "cwd": os.getcwd()}
    with open(sys.argv[1], "w") as f:
        json.dump(record, f)
    print("recorded the launch of", os.environ["CAST_COMPONENT_ID"], flush=True)
    """)


def write(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


# ------------------------------------------------------------------ configuration rules

def test_run_is_split_like_a_shell_or_taken_as_a_list(tmp_path: Path) -> None:
    config = load_config(write(tmp_path / "system.yaml", """\
        subarchitectures:
          work:
            components:
              text: {language: other, run: "node 'my component.js' --name \\"a b\\" 3"}
              words: {language: other, run: [python3, -c, "print('hi')", 7]}
              classy: {language: other, run: ./x, class: "ignored:Here", kind: managed}
        """), environ={})
    text, words, classy = config.components
    assert text.command == ["node", "my component.js", "--name", "a b", "3"]
    assert text.run == "node 'my component.js' --name \"a b\" 3"  # as written
    assert words.command == ["python3", "-c", "print('hi')", "7"]
    assert shlex.split(words.run) == words.command
    assert classy.command == ["./x"] and classy.kind == "managed"  # class: means nothing for other
    assert all(c.language == "other" and c.base_dir == tmp_path for c in config.components)


def test_other_components_mistakes_are_reported_on_their_lines(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          work:
            components:
              norun: {language: other}
              empty: {language: other, run: "  "}
              quote: {language: other, run: "node 'component.js"}
              inproc: {language: other, run: node x.js, in_process: true}
              nested: {language: other, run: [node, {a: b}]}
              cpplist: {language: cpp, run: [seg, --fast]}
              rust: {language: rust, run: cargo run}
        """)
    one(found, 4, "norun.run", "an 'other' component needs 'run: COMMAND'")
    one(found, 5, "empty.run", "an 'other' component needs 'run: COMMAND'")
    one(found, 6, "quote.run", "cannot split \"node 'component.js\" into words (No closing quotation): close the quote")
    one(found, 7, "inproc.in_process", "only python components can run in process; one of language other is its "
                                       "own process (its run: command): remove 'in_process: true'")
    one(found, 8, "nested.run", "each word of the command must be text, not a mapping")
    one(found, 9, "cpplist.run", "a cpp component's run: is one executable (a path or a name), not a list; "
                                 "for a command line with arguments use language: other")
    one(found, 10, "rust.language", "'rust' is not one of python, cpp, java, other")


def test_run_is_ignored_by_languages_that_do_not_use_it(tmp_path: Path) -> None:
    # One entry can switch language with a variable: the python choice ignores the command line.
    path = write(tmp_path / "switch.yaml", f"""\
        python_path: [{COMPONENTS}]
        subarchitectures:
          work:
            components:
              p: {{language: "${{LANG:-python}}", class: "orch_components:Producer", run: [node, producer.js]}}
        """)
    config, found = read_config(path, environ={})
    assert config is not None and not found.errors, [str(p) for p in found.items]
    assert config.components[0].command == []
    config = load_config(path, {"LANG": "other"}, environ={})
    assert config.components[0].command == ["node", "producer.js"]


# ------------------------------------------------------------------ cast check and cast run

def test_missing_executable_warns_in_check_but_fails_run(tmp_path: Path) -> None:
    cfg = write(tmp_path / "other.yaml", """\
        subarchitectures:
          vision:
            components:
              seg: {language: other, run: no-such-program --fast}
              local: {language: other, run: ./missing.sh}
        """)
    env = {"PATH": "/usr/bin:/bin"}
    out = subprocess.run([CAST, "check", str(cfg)], capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr
    assert f"{cfg}:4: warning: components.seg.run: executable 'no-such-program' is not on PATH: install it" \
        in out.stderr
    assert f"{cfg}:5: warning: components.local.run: executable '{tmp_path / 'missing.sh'}' does not exist or " \
           "is not executable" in out.stderr
    out = subprocess.run([CAST, "run", str(cfg), "--for", "1", "--runtime-dir", str(tmp_path / "rt")],
                         capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 2
    assert "error: components.seg.run" in out.stderr and "error: components.local.run" in out.stderr
    assert "nothing was started" in out.stderr


def test_launcher_resolves_the_program_like_cpp_and_keeps_the_arguments(tmp_path: Path) -> None:
    (tmp_path / "bin").mkdir()
    tool = tmp_path / "bin" / "tool"
    tool.write_text("#!/bin/sh\n")
    tool.chmod(0o755)
    config = load_config(write(tmp_path / "system.yaml", """\
        subarchitectures:
          work:
            components:
              relative: {language: other, run: "bin/tool --in data.txt"}
              bare: {language: other, run: [sh, -c, "exit 0"]}
        """), environ={})
    relative, bare = config.components
    launcher = LAUNCHERS["other"]
    assert launcher.command(relative, config, {"PATH": ""}) == [str(tool), "--in", "data.txt"]
    assert launcher.command(bare, config, {"PATH": "/usr/bin:/bin"})[1:] == ["-c", "exit 0"]
    assert Path(launcher.command(bare, config, {"PATH": "/usr/bin:/bin"})[0]).name == "sh"
    assert launcher.working_directory(relative) == tmp_path  # relative arguments mean the same as `run:`'s path


def test_cast_run_starts_an_other_component_with_the_launch_contract(tmp_path: Path) -> None:
    conf_dir = tmp_path / "conf"
    conf_dir.mkdir()
    (conf_dir / "recorder.py").write_text(RECORDER)
    record = tmp_path / "launch.json"
    cfg = write(conf_dir / "system.yaml", f"""\
        auth: {{token_ttl: 60}}
        subarchitectures:
          work:
            components:
              rec:
                language: other
                run: [{sys.executable}, recorder.py, {record}, "two words"]
                args: {{answer: 42}}
                restart: never
        """)
    out = subprocess.run([CAST, "run", str(cfg), "--for", "0.5", "--no-status", "--runtime-dir", str(tmp_path / "rt")],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    launch = json.loads(record.read_text())
    env = launch["env"]
    assert env["CAST_ENDPOINT"].startswith("127.0.0.1:")
    assert (env["CAST_COMPONENT_ID"], env["CAST_SUBARCHITECTURE"]) == ("rec", "work")
    assert json.loads(env["CAST_ARGS"]) == {"answer": 42}
    assert env["CAST_TOKEN"] and env["CAST_TOKEN_FILE"].endswith("rec.token")  # token_ttl: renewed through a file
    assert "CAST_SECRET" not in env
    assert launch["argv"] == [str(record), "two words"]
    assert launch["cwd"] == str(conf_dir)  # the directory of the file that declares it
    assert "rec | recorded the launch of rec" in out.stdout
    assert (tmp_path / "rt" / "logs" / "rec.log").read_text() == "recorded the launch of rec\n"


def test_an_other_component_is_supervised_and_restarted(tmp_path: Path, embedded: Callable[..., Embedded]) -> None:
    # A shell script that crashes on its first run and then idles until it is stopped.
    marker = tmp_path / "crashed-once"
    script = tmp_path / "flaky.sh"
    script.write_text(f'#!/bin/sh\nif [ ! -e {marker} ]; then touch {marker}; echo crashing; exit 3; fi\n'
                      'echo "second run as $CAST_COMPONENT_ID"\ntrap "exit 0" TERM\nwhile :; do sleep 0.1; done\n')
    script.chmod(0o755)
    cfg = write(tmp_path / "flaky.yaml", """\
        subarchitectures:
          work:
            components:
              flaky: {language: other, run: ./flaky.sh, restart: {policy: on-failure, backoff: 0.05}}
        """)
    run = embedded(cfg, wait=False)
    sup = wait_for(lambda: run.orchestrator.supervisor, what="the supervisor")
    flaky = sup.components["flaky"]
    wait_for(lambda: flaky.restarts == 1 and "second run as flaky" in run.text(), what="the restart")
    assert flaky.crashes == [3] and flaky.phase is Phase.RUNNING
    result = run.stop()
    assert "flaky crashed (exit code 3); restarting" in run.text()
    assert flaky.stop_code == 0
    assert result.failures == ["flaky crashed 1 time(s) (exit codes 3)"]


def test_a_full_client_runs_as_other_and_the_system_waits_for_it(
    tmp_path: Path, embedded: Callable[..., Embedded]
) -> None:
    # The Python runner, started as a plain command line: the launch contract alone lets it connect.
    cfg = write(tmp_path / "py-as-other.yaml", f"""\
        subarchitectures:
          work:
            components:
              producer:
                language: other
                run: [env, "PYTHONPATH={COMPONENTS}", {sys.executable}, -m, cast.run, "orch_components:Producer"]
                args: {{count: 2}}
        """)
    run = embedded(cfg)
    host = run.system("work").host
    who = Identity("test", "work")
    wait_for(lambda: host.exists(who, "work", "item-1"), what="the producer's entries")
    value: Any = host.get(who, "work", "item-0")
    assert StringValue.FromString(value.data).value == "item 0 from work"
    info = next(c for c in run.system("work").sessions.components() if c.id == "producer")
    assert info.language == "python" and info.session_id  # it registers as what it is
    assert run.stop().exit_code == 0
