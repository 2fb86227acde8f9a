"""The ``cast`` command's table of commands: complete, and a command loads only its own module."""

from __future__ import annotations

import json
import subprocess
import sys

from cast.cli.main import COMMANDS, build_parser


def _commands(parser: object) -> list[str]:
    sub = next(a for a in parser._actions if a.dest == "command")  # type: ignore[attr-defined]
    return list(sub.choices)


def test_the_table_names_every_command_in_the_order_help_lists_them() -> None:
    listed = [name for _, names in COMMANDS for name in names]
    assert _commands(build_parser()) == listed
    assert len(set(listed)) == len(listed)


def test_each_command_alone_builds_the_parser_of_its_module() -> None:
    for module, names in COMMANDS:
        for name in names:
            assert _commands(build_parser([name, "--help"])) == list(names), (module, name)
    # Not a command (an option, a typo): every command, so that argparse lists them in its answer.
    assert _commands(build_parser(["--version"])) == _commands(build_parser(["nope"])) == _commands(build_parser())


def test_cast_serve_does_not_load_the_other_commands_modules() -> None:
    """A server start (every test's and the orchestrator's) imports no recorder, Foxglove view or exporter."""
    code = ("import json, sys\nfrom cast.cli.main import build_parser\nbuild_parser(['serve', 'system.yaml'])\n"
            "print(json.dumps(sorted(sys.modules)))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    loaded = set(json.loads(done.stdout))
    others = {f"cast.cli.{module}" for module, _ in COMMANDS if module != "serve"}
    assert "cast.cli.serve" in loaded
    assert not others & loaded, sorted(others & loaded)
    assert not {"cast.foxglove.view", "cast.recording.recorder", "rich.console", "mcap.writer"} & loaded


def test_cast_run_loads_no_live_view_until_one_is_asked_for() -> None:
    """Most runs (every `cast run` of the suite) show no Foxglove view: foxglove-sdk and its channels wait."""
    code = ("import json, sys\nfrom cast.cli.main import build_parser\nbuild_parser(['run', 'system.yaml'])\n"
            "print(json.dumps(sorted(sys.modules)))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    loaded = set(json.loads(done.stdout))
    assert "cast.cli.run" in loaded
    assert not {"foxglove", "cast.foxglove.sink", "cast.recording.channels", "mcap"} & loaded
