"""bench.interleaved: A and B of a change in the same rounds, each frame on the side of its writer's second."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from bench import interleaved
from tests.conftest import ROOT

S = 1_000_000_000


def test_each_write_counts_for_the_side_of_its_stamps_second_and_the_first_of_each_second_is_left_out() -> None:
    sent = {
        1: 10 * S + 500_000_000,  # even second: A
        2: 11 * S + 100_000_000,  # odd second: B
        3: 11 * S + interleaved.SKIP_NS - 1,  # a side just changed: left out
        4: 12 * S + interleaved.SKIP_NS,  # A
        5: 13 * S + 900_000_000,  # B, but the second watcher never got it
    }
    stamps = {
        "one": {r: t + 1_000 * r for r, t in sent.items()},
        "two": {r: t + 2_000 for r, t in sent.items() if r != 5},
    }
    a, b = interleaved.split(sent, stamps, frames=5)
    assert a == {"one": [1.0, 4.0], "two": [2.0, 2.0]}
    assert b == {"one": [2.0, 5.0], "two": [2.0]}
    # Only the last `frames` writes, by revision.
    a, b = interleaved.split(sent, stamps, frames=2)
    assert a == {"one": [4.0], "two": [2.0]}
    assert b == {"one": [5.0], "two": []}
    assert interleaved.split(sent, stamps, frames=0) == ({"one": [], "two": []}, {"one": [], "two": []})


def test_the_b_side_is_the_odd_seconds_and_only_when_asked_for(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CAST_AB_TEST", raising=False)
    assert not interleaved.b_side("CAST_AB_TEST", 11 * S)
    monkeypatch.setenv("CAST_AB_TEST", "1")  # only "alternate" turns it on
    assert not interleaved.b_side("CAST_AB_TEST", 11 * S)
    monkeypatch.setenv("CAST_AB_TEST", "alternate")
    assert interleaved.b_side("CAST_AB_TEST", 11 * S + 999_999_999)
    assert not interleaved.b_side("CAST_AB_TEST", 12 * S)


@pytest.mark.timeout(300)
def test_a_round_on_a_real_server_gives_every_watcher_latencies_on_both_sides() -> None:
    # 90 frames at 30 Hz span three seconds: both sides, every watcher (Python, C++, Java) on each.
    out = subprocess.run(
        [sys.executable, "-m", "bench.interleaved", "CAST_AB_TEST", "--frames", "90", "--rounds", "1"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "first round: A [" in out.stdout
    pooled = re.search(r"pooled: A \[([^]]*)\].*B \[([^]]*)\]", out.stdout)
    assert pooled is not None, out.stdout
    for side in pooled.groups():
        p50s = [int(x) for x in side.split(",")]
        assert len(p50s) == 4 and all(p > 0 for p in p50s), out.stdout
