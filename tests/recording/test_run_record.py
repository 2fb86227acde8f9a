"""`cast run --record FILE`: the whole run recorded from its first change, and `make demo RECORD=`."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from cast.v1.entry_pb2 import ChangeEvent
from tests.conftest import ROOT
from tests.recording.conftest import CAST, read_indexed, read_stream


def test_cast_run_record_holds_every_change_of_the_run_from_the_first(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    done = subprocess.run([CAST, "run", "configs/pipeline.yaml", "--for", "1", "--no-status", "--record", str(path),
                           "--summary-json", str(tmp_path / "summary.json"), "--runtime-dir", str(tmp_path / "rt")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"record: recording every change of sensing, reasoning, reporting to {path}" in done.stdout
    summary = json.loads((tmp_path / "summary.json").read_text())
    read = read_indexed(path)
    changes = [ChangeEvent.FromString(m.data) for m in read.on("/cast/changes")]
    # Every revision of every SA, 1 to the last, once and in order: nothing before the recorder attached.
    for sa in summary["subarchitectures"]:
        revisions = [e.revision for e in changes if e.address.subarchitecture == sa["name"]]
        assert revisions == list(range(1, sa["revision"] + 1)), (sa["name"], revisions)
    assert len(read_stream(path)) == len(read.messages)  # indexed and stream readers agree
    end = read.metadata["cast.recording.end"]
    assert (end["reason"], end["changes"], end["gaps"]) == ("cast run stopped", str(len(changes)), "0")
    assert f"record: recorded {len(changes)} changes to {path}" in done.stdout


def test_an_existing_file_stops_cast_run_before_anything_starts(tmp_path: Path) -> None:
    path = tmp_path / "taken.mcap"
    path.write_bytes(b"mine")
    done = subprocess.run([CAST, "run", "configs/pipeline.yaml", "--for", "1", "--no-status", "--record", str(path),
                           "--runtime-dir", str(tmp_path / "rt")], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"--record {path}: the file exists" in done.stderr
    assert path.read_bytes() == b"mine" and not (tmp_path / "rt" / "logs").exists()


def test_make_demo_passes_record_to_cast_run() -> None:
    dry = subprocess.run(["make", "-n", "demo", "RECORD=demo.mcap", "DEMO_SECONDS=5"], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    line = next(x for x in dry.stdout.splitlines() if "cast run configs/demo.yaml" in x)
    assert line.endswith("--for 5 --record demo.mcap"), line
