"""bench.turns: M8's judged phase runs CAST and Zenoh at once, each writing in its own seconds."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

from bench import peer_fanout, turns
from bench.cast_cases import Server
from bench.harness import child_env
from bench.images import HISTORY_BYTES, SA, WARM_SIZE
from tests.interop.cpp_support import cpp_executable

S = 1_000_000_000
MS = 1_000_000


def test_cast_writes_in_the_even_seconds_and_the_peer_in_the_odd_ones_each_from_70_ms_in() -> None:
    assert turns.in_turn(turns.CAST, 10 * S + turns.SKIP_NS)
    assert not turns.in_turn(turns.CAST, 10 * S + turns.SKIP_NS - 1)  # the other side's last frame still read
    assert not turns.in_turn(turns.CAST, 11 * S + 500 * MS)
    assert turns.in_turn(turns.PEER, 11 * S + 999 * MS)
    assert not turns.in_turn(turns.PEER, 12 * S + 500 * MS)
    assert turns.in_turn(turns.NONE, 11 * S) and turns.in_turn(turns.NONE, 12 * S + 1)
    # The next start: now when in turn, else 70 ms into the turn's next second (this one's, when it is the turn's).
    assert turns.next_start(turns.CAST, 10 * S + 500 * MS) == 10 * S + 500 * MS
    assert turns.next_start(turns.CAST, 10 * S + 10 * MS) == 10 * S + turns.SKIP_NS
    assert turns.next_start(turns.CAST, 11 * S + 10 * MS) == 12 * S + turns.SKIP_NS
    assert turns.next_start(turns.PEER, 10 * S + 999 * MS) == 11 * S + turns.SKIP_NS
    assert turns.next_start(turns.PEER, 11 * S) == 11 * S + turns.SKIP_NS


def test_the_peers_publisher_puts_its_measured_frames_in_its_turn_after_go() -> None:
    events: list[tuple[str, int]] = []

    def put(payload: bytes) -> None:
        events.append(("put", time.monotonic_ns()))

    sent = peer_fanout.drive(put, 50, 0.02, 64, warm=3, warm_size=16, cold=2, turn=turns.PEER,
                             go=lambda: events.append(("go", time.monotonic_ns())))
    assert len(sent) == 2 + 3 + 50 and [kind for kind, _ in events].count("go") == 1
    went = [kind for kind, _ in events].index("go")
    assert went == 5  # after the cold frames and the warm-up, before the measured ones
    measured = [sent[seq] for seq in sorted(sent)[5:]]
    assert all(turns.in_turn(turns.PEER, t) for t in measured), measured
    # 50 frames 20 ms apart take 1 s, more than a turn: one began again at its start, paced from there.
    assert any(t % S - turns.SKIP_NS < 5 * MS for t in measured[1:]), measured


def test_cast_bench_writes_its_measured_frames_in_its_turn_once_told_to_go(tmp_path: Path) -> None:
    server = Server(tmp_path, [SA], limits={"history_bytes": HISTORY_BYTES})
    try:
        # 2 cold values, 3 of warm-up, then 60 measured ones 20 ms apart (1.2 s of frames: in two turns at least).
        command = [str(cpp_executable("cast_bench")), "image-write", str(WARM_SIZE), "60", "20000", "3",
                   str(WARM_SIZE), "2", "0", "0", str(turns.CAST)]
        proc = subprocess.Popen(command, env=child_env(server.env("turns-writer", SA)), stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert proc.stdin is not None and proc.stdout is not None
        assert proc.stdout.readline().strip() == "warm"
        time.sleep(0.3)  # it writes nothing measured until told
        told = time.monotonic_ns()
        proc.stdin.write("go\n")
        proc.stdin.flush()
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
    finally:
        server.stop()
    sent = {int(k): int(v) for k, v in json.loads(out.strip().splitlines()[-1]).items()}
    stamps = [sent[k] for k in sorted(sent)]
    assert len(stamps) == 2 + 3 + 60
    measured = stamps[5:]
    assert min(measured) >= told
    assert all(turns.in_turn(turns.CAST, t) for t in measured), [t % (2 * S) for t in measured]
    assert any(t % S - turns.SKIP_NS < 5 * MS for t in measured[1:]), measured  # a turn began again at its start


def test_cast_bench_refuses_a_turn_it_does_not_know() -> None:
    out = subprocess.run([str(cpp_executable("cast_bench")), "image-write", "1024", "1", "0", "0", "1024", "0",
                          "0", "0", "3"], capture_output=True, text=True, timeout=30)
    assert out.returncode == 2 and "TURN" in out.stderr
