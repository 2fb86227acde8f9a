"""The bench produces its table, JSON and plots: every row runs (`--smoke`: the smallest counts; never checks
the numbers, which `make bench` judges)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench.rows_scale import RELAY
from tests.conftest import ROOT

IDS = sorted(["D1", "M1", "M1P", "M2", "M3", "M4", "M5", "M6", "M7", "M8", "M9", "M10", "O1", "R1", "REC1"])


@pytest.mark.timeout(900)  # every row, smoke counts: about a minute on an idle 2-core machine, more on a busy one
def test_quick_benchmark_writes_table_json_and_plots(tmp_path: Path) -> None:
    scratch = tmp_path / "tmp"  # the run's TMPDIR: what it leaves there is seen
    scratch.mkdir()
    out = subprocess.run(
        [sys.executable, "-m", "bench.run", "--smoke", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=900, env={**os.environ, "TMPDIR": str(scratch)},
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert not list(scratch.glob("cast-bench-*")), "a run that ended normally removes its working directory"
    table = (tmp_path / "latest.md").read_text()
    for row_id in IDS:
        assert f"| {row_id} |" in table
    assert "cores" in table and "grpcio" in table and "Redis" in table and "CPU idle: " in table
    doc = json.loads((tmp_path / "latest.json").read_text())
    assert sorted(doc["results"]) == IDS
    for row in doc["results"].values():
        assert {"target", "met", "figures"} <= set(row)
        assert isinstance(row["met"], bool)
    # M7 measured both other clients (their benchmark programs ran), whatever the figures.
    m7 = doc["results"]["M7"]
    names = {f["name"] for f in m7["figures"]}
    assert {"C++ Add (calls/s)", "Java Add (calls/s)"} <= names, m7.get("note")
    # Java's steady-state Add comes from the interleaved blocks (cast.bench.Bench's `blocks` mode).
    assert any(n.startswith("Java Add after") and n.endswith("judged") for n in names), names
    # D1 measured every durability mode against memory only (the floor column).
    d1 = doc["results"]["D1"]["figures"]
    for mode in ("none", "batch", "always"):
        assert any(f["name"] == f"{mode}: Get (calls/s)" and f["floor"] > 0 for f in d1), d1
    # M5 measures its floor (the dispatcher's handoff alone) with it.
    m5_first = doc["results"]["M5"]["figures"][0]
    assert m5_first["name"] == "add -> callback p50 (µs)" and m5_first["floor"] > 0, m5_first
    # O1 measured the writer with metrics on against --no-metrics (the floor column).
    o1 = doc["results"]["O1"]["figures"]
    assert o1[0]["name"] == "sequential Overwrite (calls/s)" and o1[0]["floor"] > 0, o1
    # REC1 measured the recorded writer against one without (the floor), and the recorder and a replay.
    rec1 = doc["results"]["REC1"]["figures"]
    assert rec1[0]["floor"] > 0 and rec1[1]["name"] == "recorder throughput (changes/s)" and rec1[1]["value"] > 0
    # M1 against the stream ping-pong too; M3 against Zenoh; M8 with its four watchers at both sizes, Zenoh (the
    # peer column) and iceoryx2 (the floor column), the bare relay beside them, the watcher on another host; M9 at each
    # count.
    m1_names = {f["name"] for f in doc["results"]["M1"]["figures"]}
    assert "add_per_s (calls/s) vs stream ping-pong" in m1_names, m1_names
    assert doc["results"]["M3"]["figures"][0]["peer"] > 0, doc["results"]["M3"]
    m8 = {f["name"]: f for f in doc["results"]["M8"]["figures"]}
    for watcher in ("Python 1", "C++", "Java", "Python 2"):
        assert f"1 MiB, queue, 30 Hz, {watcher}: p50 (µs)" in m8, (m8, doc["results"]["M8"].get("note"))
        assert m8[f"1 MiB, queue, 30 Hz, {watcher}: p50 (µs)"]["peer"] > 0
        assert m8[f"1 MiB, queue, 30 Hz, {watcher}: p50 (µs)"]["floor"] > 0
        assert f"6 MiB, queue, 30 Hz, {watcher}: p99 (µs)" in m8
    b2b = m8["1 MiB, queue, back to back: MB/s delivered, all watchers"]
    assert b2b["floor"] > 0 and b2b["peer"] > 0, b2b
    assert any(name.startswith("1 MiB, 30 Hz, Python, other host: MB received as bytes") for name in m8), m8
    assert "iceoryx2, 1 MiB, back to back: MB/s delivered, all subscribers" in m8
    assert m8[f"{RELAY}: p50 (µs), median of subscribers"]["value"] > 0, m8
    m9 = {f["name"] for f in doc["results"]["M9"]["figures"]}
    assert {"10 sessions: p99 (µs)", "20 sessions: p99 (µs)"} <= m9, doc["results"]["M9"]
    # M10: the ROS bridge beside rclpy -> rclpy (the peer column), both sizes.
    m10 = {f["name"]: f for f in doc["results"]["M10"]["figures"]}
    for size in ("1 KiB", "1 MiB"):
        assert m10[f"{size}: ROS -> WM p50 (µs)"]["peer"] > 0, doc["results"]["M10"]
        assert m10[f"{size}: bare gRPC unary echo at 30 Hz, p50 (µs)"]["value"] > 0, doc["results"]["M10"]
        assert m10[f"{size}: stamp -> the bridge's write acknowledged, p50 (µs)"]["value"] > 0
    for plot in ("latency_cdf.png", "fanout.png", "wm_size.png", "many_components.png"):
        assert (tmp_path / plot).read_bytes()[:4] == b"\x89PNG"
