"""`cast info`: what a recording holds (SAs, types, counts per channel and operation, time span, gaps), as tables
and as JSON."""

from __future__ import annotations

import json
import re

from cast.recording.info import iso
from tests.recording.conftest import Scenario, read_indexed
from tests.recording.conftest import cast as cast_cli


def test_info_as_json(scenario: Scenario) -> None:
    out = cast_cli("info", str(scenario.path), "--json")
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert info["system"] == "test" and info["file"] == str(scenario.path) and info["gaps"] == []
    rows = {r["subarchitecture"]: r for r in info["subarchitectures"]}
    assert list(rows) == ["vision", "language", "motor"]
    assert {k: rows["vision"][k] for k in ("changes", "add", "overwrite", "delete", "first_revision",
                                           "last_revision")} == {"changes": 5, "add": 3, "overwrite": 1, "delete": 1,
                                                                 "first_revision": 1, "last_revision": 5}
    assert (rows["language"]["changes"], rows["language"]["add"]) == (1, 1)
    tasks = rows["motor"]["changes"]
    assert tasks >= 1
    channels = {c["topic"]: c for c in info["channels"]}
    assert {t: c["messages"] for t, c in channels.items()} == {
        "/vision/cast.testing.Pose": 3, "/vision/cast.testing.Counter": 1, "/motor/cast.v1.Task": tasks,
        "/language/cast.testing.Pose": 1, "/cast/changes": 6 + tasks}
    assert channels["/vision/cast.testing.Pose"]["schema"] == "registered"
    assert info["changes"] == 6 + tasks
    times = [m.log_time for m in read_indexed(scenario.path).on("/cast/changes")]
    assert (info["start"], info["end"]) == (iso(min(times)), iso(max(times)))  # the changes', not the recorder's
    assert info["duration_s"] == round((max(times) - min(times)) / 1e9, 6)
    assert info["stop_reason"] == "SIGINT" and info["recorded_from"] <= info["start"]


def test_info_as_tables(scenario: Scenario) -> None:
    out = cast_cli("info", str(scenario.path))
    assert out.returncode == 0, out.stderr
    text = out.stdout
    assert text.startswith(f"{scenario.path}: system 'test' at 127.0.0.1:") and "0 gap(s)" in text
    assert re.search(r"vision\s*│\s*5\s*│\s*3\s*│\s*1\s*│\s*1\s*│\s*1\.\.5", text), text
    assert "/vision/cast.testing.Counter" in text and "cast.testing.Counter" in text and "registered" in text
