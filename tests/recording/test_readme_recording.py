"""The README's recording section runs as written (the recording shortened; the replay into a second system)."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter

from tests.conftest import VENV_BIN
from tests.recording.conftest import cli_env, entries
from tests.test_readme import blocks, section

BIN = str(VENV_BIN)


def test_the_readme_commands_record_inspect_and_replay(server_factory: Any, tmp_path: Path) -> None:
    lines = blocks(section("Recording and replaying: `cast record`, `cast info`, `cast replay`"), "sh")[0]
    record_line, info_line, replay_line, demo_line = lines.strip().splitlines()
    assert demo_line.startswith("make demo RECORD=demo.mcap")  # tests/recording/test_run_record.py runs it dry
    assert record_line.startswith("cast record -o run.mcap --for 60")
    robot = server_factory({"system": "robot", "subarchitectures": {"vision": {}}})
    desk = server_factory({"system": "desk", "subarchitectures": {"vision": {}}})

    def command(line: str, endpoint: str) -> dict[str, Any]:
        return {"args": ["bash", "-c", line.split("#")[0].replace("--for 60", "--for 2")], "cwd": tmp_path,
                "env": cli_env(CAST_ENDPOINT=endpoint, PATH=f"{BIN}:/usr/bin:/bin"), "text": True}

    def run(line: str, endpoint: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(**command(line, endpoint), capture_output=True, timeout=60)

    recorder = subprocess.Popen(**command(record_line, robot.endpoint), stderr=subprocess.PIPE)
    writer = robot.connect("w", "vision")
    try:
        assert recorder.stderr is not None
        assert "cast record: recording vision" in recorder.stderr.readline()
        for i in range(3):
            writer.add(f"e{i}", Counter(value=i))
        assert recorder.wait(60) == 0, recorder.stderr.read()
    finally:
        writer._cast_close()
        recorder.kill()
        recorder.communicate()
    out = run(info_line, robot.endpoint)
    assert out.returncode == 0 and "3 changes" in out.stdout, out.stdout + out.stderr
    out = run(replay_line, desk.endpoint)
    assert out.returncode == 0, out.stderr
    assert entries(desk, "vision") == entries(robot, "vision") != {}
