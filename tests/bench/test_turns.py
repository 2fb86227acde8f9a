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
from bench.other_clients import java_command
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


def test_three_sides_take_every_third_second() -> None:
    assert [turns.in_turn(turn, 12 * S + turns.SKIP_NS, sides=3) for turn in (1, 2, 3)] == [True, False, False]
    assert [turns.next_start(turn, 13 * S, sides=3) for turn in (1, 2, 3)] == [
        15 * S + turns.SKIP_NS, 13 * S + turns.SKIP_NS, 14 * S + turns.SKIP_NS]


def _latency_writes(tmp_path: Path, command: list[str], turn: int, sides: int) -> list[int]:
    """The stamps of a `write` mode run of 150 spaced overwrites (2 ms apart) after 50 back to back, in a turn."""
    server = Server(tmp_path, [SA])
    try:
        out = subprocess.run([*command, "write", "150", "2", "50", str(turn), str(sides)],
                             env=child_env(server.env("turns-latency-writer", SA)), capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
    finally:
        server.stop()
    sent = {int(k): int(v) for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()}
    return [sent[k] for k in sorted(sent)]


def test_cast_bench_writes_its_spaced_overwrites_in_its_turn_of_three(tmp_path: Path) -> None:
    stamps = _latency_writes(tmp_path, [str(cpp_executable("cast_bench"))], 2, 3)
    assert len(stamps) == 149  # the add is not stamped
    assert all(turns.in_turn(2, t, sides=3) for t in stamps), [t % (3 * S) for t in stamps]


def test_the_java_bench_writes_its_spaced_overwrites_in_its_turn_of_three(tmp_path: Path) -> None:
    command = java_command()
    assert isinstance(command, list), command
    stamps = _latency_writes(tmp_path, command, 3, 3)
    assert len(stamps) == 149
    assert all(turns.in_turn(3, t, sides=3) for t in stamps), [t % (3 * S) for t in stamps]


def test_cast_bench_refuses_a_turn_past_its_sides() -> None:
    out = subprocess.run([str(cpp_executable("cast_bench")), "write", "10", "2", "0", "4", "3"],
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 2 and "TURN SIDES" in out.stderr
