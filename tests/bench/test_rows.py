"""The benchmark code that needs no server: delivery figures, row building and target checks."""

from __future__ import annotations

import mmap
import os
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import pytest

from bench import peer_fanout, turns
from bench.checksum import expected_cast, expected_frames, word_sum
from bench.delivery_stats import parse_watcher, totals, watcher_figures
from bench.images import REMOTE, WATCHERS, _halves, figures
from bench.many_components import split
from bench.peer_fanout import END, WARM, Receiver, drive, frame
from bench.report import cpu_idle, plot_panels
from bench.rows import Results, rows
from bench.rows_calls import m1_row, m1p_row, m3_row
from bench.rows_scale import RELAY, m8_memory_bound, m8_misses, m8_row, m9_misses, m9_row
from bench.server_memory import QUIET_AT_NS, ServerMemory, shared_bytes
from bench.stream_cases import window

MS = 1_000_000  # ns


def test_watcher_figures_latency_losses_and_rate() -> None:
    sent = {10: 0, 11: 10 * MS, 12: 20 * MS, 13: 30 * MS}
    got = parse_watcher({"stamps": {"10": 1 * MS, "11": 12 * MS, "13": 33 * MS}, "bytes": 3_000_000, "events": 5})
    f = watcher_figures(sent, got, extra_events=2)
    assert f["received"] == 3 and f["lost"] == 1 and f["skipped"] == 0
    assert f["p50_us"] == 2000.0 and f["p99_us"] == 3000.0
    assert f["mb_per_s"] == 90.9  # 3 MB from the first write (0) to the last arrival (33 ms)


def test_a_latest_watcher_that_skipped_is_not_lost() -> None:
    sent = {1: 0, 2: MS, 3: 2 * MS}
    got = parse_watcher({"stamps": {"3": 3 * MS}, "bytes": 100, "events": 3, "skipped": 2})  # add, rev 3, delete
    assert watcher_figures(sent, got, extra_events=2)["lost"] == 0
    got["skipped"] = 1
    assert watcher_figures(sent, got, extra_events=2)["lost"] == 1


def test_totals_add_every_watcher_over_the_whole_span() -> None:
    sent = {0: 0, 1: 10 * MS}
    watchers = [{"stamps": {0: 5 * MS, 1: 20 * MS}, "bytes": 2_000_000}, {"stamps": {0: 6 * MS}, "bytes": 1_000_000}]
    assert totals(sent, watchers) == {"mb_per_s": 150.0, "bytes": 3_000_000}


def test_m8_judges_the_frames_after_the_warm_up_and_shows_the_first_seconds_apart() -> None:
    # Revisions 1-2 cold (9 ms each), 3-5 the warm-up burst (50 ms: queued), 6-15 measured (1 ms; the first
    # tenth, revision 6, dropped as before). The watcher missed warm-up revision 4: lost, though not measured.
    sent = {r: r * 100 * MS for r in range(1, 16)}
    delay = {1: 9, 2: 9, 3: 50, 5: 50, 6: 7, **{r: 1 for r in range(7, 16)}}
    got = {"Java": parse_watcher({"stamps": {str(r): sent[r] + d * MS for r, d in delay.items()},
                                  "bytes": 14 * 1000, "events": 14 + 2, "checksum": 5})}
    out = figures(sent, got, 2, lambda g: 5, 1000, warm=3, cold=2)
    java = out["watchers"]["Java"]
    assert java["p50_us"] == java["p99_us"] == 1000.0  # neither the burst nor the cold frames
    assert java["cold_p50_us"] == 9000.0 and java["lost"] == 1 and java["received"] == 14 and java["checksum_ok"]
    assert out["frames"] == 10 and out["total"]["bytes"] == 10 * 1000  # MB/s of the measured frames only
    whole = figures(sent, got, 2, lambda g: 5, 1000)  # without the parts: the burst is in the latencies
    assert whole["watchers"]["Java"]["p99_us"] == 50_000.0 and "cold_p50_us" not in whole["watchers"]["Java"]


def _phase(latencies_ms: list[int], lost: int = 0, checksum_ok: bool = True, peak: int = 100) -> dict[str, Any]:
    """A phase as figures() gives it: one watcher, Java, with these latencies."""
    sent = {r: r * 100 * MS for r in range(1, len(latencies_ms) + 1)}
    got = {"Java": parse_watcher({"stamps": {str(r): sent[r] + d * MS for r, d in zip(sent, latencies_ms, strict=True)},
                                  "bytes": 1000 * len(sent), "events": len(sent) + 2 - lost, "shared": len(sent)})}
    out = figures(sent, got, 2, lambda g: 0 if checksum_ok else 1, 1000)
    return {**out, "size": 1000, "server_memory": {"peak": peak, "private": 1, "shared": 1}, "missing": {}}


def test_the_judged_phase_shows_each_sides_p50_over_each_half_of_its_frames() -> None:
    # 20 measured frames, the first 2 left out as settling: 9 of 1 ms, then 9 of 3 ms.
    result = _phase([1] * 11 + [3] * 9)
    assert _halves(result) == [{"Java": 1000.0}, {"Java": 3000.0}]
    assert _halves({"error": "Java watcher exited 1"}) == [{}, {}]


def test_the_peers_get_the_same_cold_frames_warm_up_and_pause(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(peer_fanout, "SETTLE_S", 0.05)
    monkeypatch.setattr(peer_fanout, "WARM_BURST", 2)
    monkeypatch.setattr(peer_fanout, "WARM_PAUSE_S", 0.05)
    seqs: list[int] = []
    sizes: list[int] = []

    def put(payload: bytes) -> None:
        seqs.append(int.from_bytes(payload[:8], "little"))
        sizes.append(len(payload))

    sent = drive(put, 4, 0.1, 64, warm=5, warm_size=16, cold=2)
    assert list(sent) == seqs == list(range(11))  # numbered on: the reader tells the parts apart by number
    assert sizes == [64] * 2 + [16] * 5 + [64] * 4
    assert expected_frames(seqs, 64, dict.fromkeys(range(2, 7), 16)) == sum(word_sum(frame(q, z)) for q, z in
                                                                             zip(seqs, sizes, strict=True)) % 2**64
    assert sent[1] - sent[0] >= 99 * MS and sent[10] - sent[7] >= 3 * 99 * MS  # cold and measured frames paced
    # The warm-up (2-6) in bursts of two back to back, a pause after each but the last: 2 3 | 4 5 | 6.
    assert sent[3] - sent[2] < 100 * MS and sent[5] - sent[4] < 100 * MS  # paced, a gap would take 100 ms
    assert sent[4] - sent[3] >= 50 * MS and sent[6] - sent[5] >= 50 * MS  # the pauses between bursts
    assert sent[6] - sent[2] < 2 * 50 * MS + 100 * MS  # and no more: two pauses, the rest back to back
    assert sent[7] - sent[6] >= 50 * MS  # the pause after the warm-up


def test_receiver_stamps_data_and_ends_at_end(capsys: pytest.CaptureFixture[str]) -> None:
    r = Receiver()
    r.on_message(frame(WARM, 16))
    r.on_message(frame(WARM, 16))
    r.on_message(frame(7, 1000))
    assert not r.done.is_set()
    r.on_message(frame(END, 16))
    assert r.done.is_set() and list(r.stamps) == [7] and r.bytes == 1000
    assert capsys.readouterr().out == "ready\n"  # once


def test_a_reader_of_every_byte_sums_what_was_sent(capsys: pytest.CaptureFixture[str]) -> None:
    r = Receiver(read_all=True)
    for seq in (3, 4):
        r.on_message(memoryview(frame(seq, 1003)))
    r.on_message(frame(END, 16))
    assert r.checksum == expected_frames([3, 4], 1003) != expected_frames([3, 5], 1003)
    r.report()
    assert f'"checksum": {r.checksum}' in capsys.readouterr().out


def test_the_checksum_is_the_sum_of_little_endian_words_and_the_writers_values_are_known() -> None:
    data = bytes(range(256)) * 4 + b"\xff\x01\x02"
    reference = sum(int.from_bytes(data[i: i + 8], "little") for i in range(0, 1024, 8)) + 0xFF + 1 + 2
    assert word_sum(data) == reference % 2**64
    assert word_sum(b"\xff" * 16) == (2 * (2**64 - 1)) % 2**64  # modulo 2**64, as C++ and Java wrap
    size = (1 << 20) + 5
    values = [bytes([1]) * size, bytes([2]) * size]
    sent = {10: 0, 11: 0, 12: 0}  # the overwrites, by revision: values 0, 1, 0
    assert expected_cast(sent, [11, 12], size) == (word_sum(values[1]) + word_sum(values[0])) % 2**64
    assert expected_cast(sent, [11, 12], size) != expected_cast(sent, [10, 12], size)
    assert expected_frames([7], size) == word_sum(frame(7, size))
    # M8's warm-up values are smaller: the sum counts each revision at its own size, the 1s and 2s alternating on.
    assert expected_cast(sent, [11, 12], size, {11: 13}) == (word_sum(bytes([2]) * 13) + word_sum(values[0])) % 2**64


def test_split_shares_sessions_evenly_without_empty_processes() -> None:
    assert split(10, 4) == [3, 3, 2, 2]
    assert split(500, 4) == [125] * 4
    assert split(2, 4) == [1, 1]


def test_window_never_has_more_than_in_flight_unsettled() -> None:
    live: list[Future[int]] = []
    peak = 0

    class Lazy(Future[int]):
        """Settled only when its result is asked for, as a reply that arrives when waited on."""

        def result(self, timeout: float | None = None) -> int:
            if not self.done():
                self.set_result(0)
                live.remove(self)
            return super().result(timeout)

    calls: list[int] = []

    def submit(i: int) -> Future[int]:
        nonlocal peak
        calls.append(i)
        f = Lazy()
        live.append(f)
        peak = max(peak, len(live))
        return f

    window(submit, 10, 3)
    assert calls == list(range(10)) and peak == 3 and live == []
    failing: Future[int] = Future()
    failing.set_exception(ValueError("refused"))
    with pytest.raises(ValueError, match="refused"):
        window(lambda i: failing, 2, 1)


def _results(**overrides: Any) -> Results:
    base: dict[str, Any] = {
        "tcp": {"p50_us": 50.0, "round_trips_per_s": 20000},
        "peer": {"set_ops_per_s": 10000, "get_ops_per_s": 10000, "notification": {"p50_us": 150.0, "p99_us": 300.0}},
        "echo": {"unary_calls_per_s": 1000, "stream_calls_per_s": 1600, "unary_p50_us": 900.0,
                 "unary_spaced_p50_us": 1000.0, "stream_ping_pong_p50_us": 550.0},
        "m1": {"add_per_s": 1400, "get_per_s": 900, "overwrite_per_s": 1350},
        "m3": {"p50_us": 950.0, "p99_us": 1500.0, "lost": 0},
        "zenoh": {"p50_us": 400.0, "p99_us": 600.0},
    }
    base.update(overrides)
    empty: dict[str, Any] = {}
    return Results(base["tcp"], base["peer"], base["echo"], base["m1"], empty, base["m3"], empty, empty, empty, empty,
                   empty, empty, empty, empty, zenoh=base["zenoh"])


def test_m1_needs_both_floors_for_streamed_calls_and_the_unary_one_for_get() -> None:
    assert m1_row(_results())["met"]
    assert not m1_row(_results(m1={"add_per_s": 1250, "get_per_s": 900, "overwrite_per_s": 1350}))["met"]  # < 1.3 x
    slow_stream = {**_results().echo, "stream_calls_per_s": 1800}  # 1350 < 0.8 x 1800
    assert not m1_row(_results(echo=slow_stream))["met"]
    assert not m1_row(_results(m1={"add_per_s": 1400, "get_per_s": 700, "overwrite_per_s": 1350}))["met"]
    names = [f["name"] for f in m1_row(_results())["figures"]]
    assert "add_per_s (calls/s) vs stream ping-pong" in names and "get_per_s (calls/s) vs stream ping-pong" not in names


def test_m1p_is_three_times_sequential() -> None:
    assert m1p_row({"in_flight": 64, "sequential_per_s": 1000, "pipelined_per_s": 3000})["met"]
    assert not m1p_row({"in_flight": 64, "sequential_per_s": 1000, "pipelined_per_s": 2999})["met"]


def test_m3_against_the_spaced_floor_zenoh_and_the_p99_line() -> None:
    assert m3_row(_results())["met"]
    assert not m3_row(_results(m3={"p50_us": 1001.0, "p99_us": 1500.0, "lost": 0}))["met"]  # > 1.0 x floor
    assert not m3_row(_results(zenoh={"p50_us": 300.0, "p99_us": 500.0}))["met"]  # > 3 x Zenoh
    assert not m3_row(_results(m3={"p50_us": 950.0, "p99_us": 2001.0, "lost": 0}))["met"]
    failed = m3_row(_results(zenoh={"error": "no zenoh"}))
    assert not failed["met"] and "no zenoh" in failed["note"]


def _watchers(p50: float = 900.0, p99: float = 4000.0, labels: tuple[str, ...] = WATCHERS) -> dict[str, Any]:
    one = {"p50_us": p50, "p99_us": p99, "lost": 0, "skipped": 0, "mb_per_s": 30.0, "received": 60,
           "bytes": 60 << 20, "checksum_ok": True, "shared": 60}
    return {label: dict(one) for label in labels}


def _m8() -> dict[str, Any]:
    """An M8 result that meets every target; each test breaks one thing."""
    def phase(p99: float = 4000.0, mb: float = 2000.0) -> dict[str, Any]:
        return {"watchers": _watchers(p99=p99), "total": {"mb_per_s": mb, "bytes": 1}, "frames": 60,
                "size": 1 << 20, "server_memory": {"peak": 200 << 20, "private": 90 << 20, "shared": 110 << 20},
                "missing": {}}

    def peer(p50: float = 1000.0, mb: float = 1500.0) -> dict[str, Any]:
        return {"watchers": _watchers(p50=p50, p99=3000.0, labels=("subscriber 1", "subscriber 2")),
                "total": {"mb_per_s": mb, "bytes": 1}, "frames": 60, "size": 1 << 20}

    remote = phase()
    remote["watchers"] = _watchers(labels=(REMOTE,))
    remote["watchers"][REMOTE]["shared"] = 0
    return {"size": 1 << 20, "big": 6 << 20, "hz": 30, "history_bytes": 64 << 20, "server_memory_idle": 80 << 20,
            "floor": [{"mb_per_s": 300.0, "p50_us": 3000.0}],
            "cast_queue_hz": phase(), "cast_queue_hz_6m": phase(p99=9000.0), "cast_queue_b2b": phase(),
            "cast_latest_b2b": phase(), "cast_remote": remote,
            "zenoh_hz": peer(), "zenoh_hz_6m": peer(p50=5000.0), "zenoh_b2b": peer(),
            "iceoryx2_hz": peer(p50=150.0), "iceoryx2_b2b": peer(mb=6000.0), "relay_hz": peer(p50=600.0)}


def test_m8_is_met_when_every_target_is() -> None:
    assert m8_misses(_m8()) == [] and m8_row(_m8())["met"]
    assert not m8_row({"error": "C++ not built"})["met"]


@pytest.mark.parametrize(
    ("change", "miss"),
    [
        (lambda m: m["cast_queue_hz"]["watchers"]["Java"].update(p50_us=1001.0), "Java p50 1001 µs > 1.0 x Zenoh"),
        (lambda m: m["cast_queue_hz"]["watchers"]["C++"].update(p99_us=5001.0), "C++ p99 5001 µs > 5000"),
        (lambda m: m["cast_queue_hz_6m"]["watchers"]["Python 2"].update(p99_us=10_001.0), "p99 10001 µs > 10000"),
        (lambda m: m["cast_queue_hz_6m"]["watchers"]["Python 1"].update(lost=1), "30 Hz: Python 1 lost 1"),
        (lambda m: m["cast_latest_b2b"]["watchers"]["C++"].update(checksum_ok=False), "C++'s checksum"),
        (lambda m: m["cast_latest_b2b"]["watchers"]["Java"].update(lost=3, watch_ended="HistoryExpiredError: x"),
         "Java lost 3 (its watch ended: HistoryExpiredError: x)"),
        (lambda m: m["cast_queue_b2b"]["total"].update(mb_per_s=1499.0), "1499.0 MB/s to the four < 1.0 x Zenoh"),
        (lambda m: m["cast_queue_b2b"].update(missing={"Java": "Java not built"}), "Java: Java not built"),
        (lambda m: m.update(cast_queue_hz_6m={"error": "history overrun"}), "6 MiB, queue, 30 Hz: history overrun"),
        (lambda m: m["cast_remote"]["watchers"][REMOTE].update(bytes=1), "received 1 bytes, not 60 x 1048576"),
        (lambda m: m["cast_remote"]["watchers"][REMOTE].update(shared=3), "got 3 values by shared memory"),
        (lambda m: m["cast_remote"]["watchers"][REMOTE].update(lost=2), "other host: Python, other host lost 2"),
        (lambda m: m.update(cast_remote={"error": "`ip netns add` failed"}), "`ip netns add` failed"),
        (lambda m: m.update(iceoryx2_hz={"error": "iceoryx2 not measured"}), "iceoryx2, 1 MiB, 30 Hz: iceoryx2 not"),
        (lambda m: m.update(zenoh_b2b={"error": "no zenoh"}), "Zenoh, 1 MiB, back to back: no zenoh"),
        (lambda m: m.update(relay_hz={"error": "relay did not start"}), "bare Python relay (CAST's two hops"),
        (lambda m: m["cast_latest_b2b"]["server_memory"].update(peak=m8_memory_bound(m) + 1), "server memory peak"),
    ],
)
def test_m8_misses_each_target(change: Callable[[dict[str, Any]], None], miss: str) -> None:
    m8 = _m8()
    change(m8)
    misses = m8_misses(m8)
    assert len(misses) == 1 and miss in misses[0], misses
    row = m8_row(m8)
    assert not row["met"] and miss in row["note"]


def test_m8_figures_name_the_peers_and_say_what_was_not_measured() -> None:
    figures = {f["name"]: f for f in m8_row(_m8())["figures"]}
    p50 = figures["1 MiB, queue, 30 Hz, Java: p50 (µs)"]
    assert (p50["value"], p50["floor"], p50["peer"]) == (900.0, 150.0, 1000.0)  # floor iceoryx2, peer Zenoh
    b2b = figures["1 MiB, queue, back to back: MB/s delivered, all watchers"]
    assert (b2b["floor"], b2b["peer"]) == (6000.0, 1500.0)
    relay = figures[f"{RELAY}: p50 (µs), median of subscribers"]
    assert relay["value"] == 600.0  # what the path costs without CAST's rules: shown, not judged
    broken = _m8()
    broken["iceoryx2_b2b"] = {"error": "iceoryx2 not measured: no module"}
    assert any(name.startswith("iceoryx2, 1 MiB, back to back: not measured (iceoryx2 not measured: no module")
               for name in (f["name"] for f in m8_row(broken)["figures"]))


def test_m8_shows_the_first_seconds_beside_the_peers_without_judging_them() -> None:
    m8 = _m8()
    m8["cold_s"] = 2.0
    for w in m8["cast_queue_hz"]["watchers"].values():
        w.update(cold_p50_us=50_000.0, cold_p99_us=90_000.0)  # far past every target: still not a miss
    for key, p50 in (("zenoh_hz", 1200.0), ("iceoryx2_hz", 200.0)):
        for w in m8[key]["watchers"].values():
            w.update(cold_p50_us=p50, cold_p99_us=4 * p50)
    assert m8_misses(m8) == []
    figures_ = {f["name"]: f for f in m8_row(m8)["figures"]}
    cold = figures_["1 MiB, queue, 30 Hz, first 2 s (cold, not judged), Java: p50 (µs)"]
    assert (cold["value"], cold["floor"], cold["peer"]) == (50_000.0, 200.0, 1200.0)
    assert not any("first" in name for name in (f["name"] for f in m8_row(_m8())["figures"]))  # none measured


def test_m8_shows_each_half_of_the_judged_phase_beside_zenohs_same_half() -> None:
    m8 = _m8()
    m8["cast_queue_hz"]["halves"] = [{"Python 1": 1100.0, "Java": 1300.0}, {"Python 1": 1250.0, "Java": 1200.0}]
    m8["zenoh_hz"]["halves"] = [{"subscriber 1": 1000.0, "subscriber 2": 1200.0}, {"subscriber 1": 1150.0,
                                                                                   "subscriber 2": 1150.0}]
    halves = [f for f in m8_row(m8)["figures"] if " half of the turns: " in f["name"]]
    assert [(f["value"], f["peer"]) for f in halves] == [(1300.0, 1100.0), (1250.0, 1150.0)]
    assert halves[0]["name"].startswith("1 MiB, queue, 30 Hz, the first half of the turns: the slowest watcher's "
                                        "p50 (Java")
    assert m8_misses(m8) == []  # shown, not judged: the whole phase's figures are


def _m9(p99_10: float, p99_500: float, lost: int = 0) -> dict[str, Any]:
    def at(n: int, p99: float) -> dict[str, Any]:
        return {"sessions": n, "p50_us": p99 / 2, "p99_us": p99, "lost": lost, "register_s": 0.1,
                "rss_per_session_kib": 50.0, "busy_cpu": 0.2}

    return {"counts": {"10": at(10, p99_10), "100": at(100, p99_10), "500": at(500, p99_500)}, "processes": 4}


def test_m9_compares_the_largest_count_with_the_smallest() -> None:
    assert m9_misses(_m9(2000, 6000)) == [] and m9_row(_m9(2000, 6000))["met"]
    assert m9_misses(_m9(2000, 6001))
    assert m9_misses(_m9(2000, 3000, lost=1))
    failed = _m9(2000, 3000)
    failed["counts"]["500"] = {"sessions": 500, "error": "refused"}
    assert any("refused" in m for m in m9_misses(failed))


def test_every_row_has_an_id_a_target_and_a_verdict() -> None:
    r = _results()
    r.m1p = {"in_flight": 64, "sequential_per_s": 1000, "pipelined_per_s": 4000}
    r.m8, r.m9 = _m8(), _m9(2000, 3000)
    r.m2 = {"entries_per_s": 50000}
    r.m4 = {"delivered_per_s": 60000, "lost": 0, "out_of_order": 0, "duplicates": 0}
    r.m5 = {"add_to_callback": {"p50_us": 40, "p99_us": 90}, "handoff": {"p50_us": 30}, "get": {"p50_us": 1}}
    r.m6 = {"entries": 1000, "server_rss_mib": 100, "get_all_10_p50_ms": 1, "add_per_s_at_small": 1000,
            "add_per_s_at_full": 950, "add_rate_ratio": 0.95}
    r.m7 = {"id": "M7", "target": "-", "figures": [], "met": True}
    r.d1 = {m: {"add_per_s": 1, "get_per_s": 1, "overwrite_per_s": 1, "batch_entries_per_s": 1, "p50_us": 1,
                "lost": 0} for m in ("memory", "none", "batch", "always")}
    r.r1 = {"events": 1, "batch_events_per_s_with": 1, "batch_events_per_s_without": 1, "sequential_per_s_with": 1,
            "sequential_per_s_without": 1, "batch_ratio": 1, "sequential_ratio": 1}
    r.o1 = {"id": "O1", "target": "-", "figures": [], "met": True}
    r.rec1 = {"id": "REC1", "target": "-", "figures": [], "met": True}
    table = rows(r)
    assert [row["id"] for row in table][:10] == ["M1", "M1P", "M2", "M3", "M4", "M5", "M6", "M7", "M8", "M9"]
    for row in table:
        assert isinstance(row["met"], bool) and row["target"]


def test_plot_panels_writes_a_png_with_a_log_panel(tmp_path: Path) -> None:
    out = tmp_path / "m9.png"
    plot_panels(out, [10, 100, 500], {"latency (µs)": {"p50": [1, 10, 100], "p99": [2, 20, 200]},
                                      "cpu": {"cpu": [0.1, 0.5, 0.7]}}, "sessions", "M9", log_y=["latency (µs)"])
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_the_server_memory_counts_each_memory_file_once_at_its_full_size() -> None:
    before = shared_bytes(os.getpid())
    fd = os.memfd_create("m8-test")
    try:
        os.ftruncate(fd, 3 << 20)
        first = mmap.mmap(fd, 3 << 20)
        second = mmap.mmap(fd, 1 << 20)  # a second mapping of the same file: not counted twice
        assert shared_bytes(os.getpid()) - before == 3 << 20  # mapped and open, untouched: its whole size
        os.close(fd)
        fd = -1
        assert shared_bytes(os.getpid()) - before == 3 << 20  # mapped only
        first.close()
        second.close()
        assert shared_bytes(os.getpid()) == before
    finally:
        if fd >= 0:
            os.close(fd)


def test_m8_finds_the_line_where_a_watchers_library_said_its_watch_ended() -> None:
    import tempfile

    from bench.images import _watch_ended

    java = ("checksum warmed up (0)\nNov 29, 2026 1:58:37 PM cast.client.Component watchFailed\nSEVERE: m8-w2: change "
            "delivery stopped: HistoryExpiredError: subarchitecture 'images': revision 20767 is gone\n")
    for text, found in ((java, "change delivery stopped: HistoryExpiredError"),
                        ("image_watcher: the watch failed: OUT_OF_RANGE\n", "the watch failed"), ("ready\n", "")):
        with tempfile.TemporaryFile("w+") as log:
            log.write(text)
            assert (found in _watch_ended(log)) if found else _watch_ended(log) == ""


def test_cpu_idle_names_the_driver_its_states_halt_polling_and_the_latency_limit(tmp_path: Path) -> None:
    cpus, params, qos = tmp_path / "cpu", tmp_path / "haltpoll", tmp_path / "cpu_dma_latency"
    (cpus / "cpuidle").mkdir(parents=True)
    (cpus / "cpuidle" / "current_driver").write_text("haltpoll\n")
    for i, (name, latency) in enumerate([("POLL", 0), ("haltpoll idle", 1)] * 6):  # state10 sorts after state2
        state = cpus / "cpu0" / "cpuidle" / f"state{i}"
        state.mkdir(parents=True)
        (state / "name").write_text(f"{name}\n" if i < 2 else f"S{i}\n")
        (state / "latency").write_text(f"{latency if i < 2 else i * 10}\n")
    params.mkdir()
    (params / "guest_halt_poll_ns").write_text("0\n")
    qos.write_bytes((2_000_000_000).to_bytes(4, "little"))
    states = "POLL 0 µs, haltpoll idle 1 µs, " + ", ".join(f"S{i} {i * 10} µs" for i in range(2, 12))
    assert cpu_idle(cpus, params, qos) == f"haltpoll ({states}); halt polling 0 ns; CPU latency limit none"
    qos.write_bytes((0).to_bytes(4, "little"))  # a process holds /dev/cpu_dma_latency at 0: idle CPUs poll
    assert cpu_idle(cpus, params, qos).endswith("; CPU latency limit 0 µs")
    # Another driver: no halt polling; a limit that cannot be read (not root) is left out.
    (cpus / "cpuidle" / "current_driver").write_text("intel_idle\n")
    assert cpu_idle(cpus, params, tmp_path / "absent") == f"intel_idle ({states})"
    assert cpu_idle(tmp_path / "none", params, tmp_path / "absent") == "unknown"


def test_the_server_memory_sampler_reads_the_shared_memory_again_when_it_stops() -> None:
    memory = ServerMemory(os.getpid())  # its first sample: before the memory file below
    fd = os.memfd_create("m8-test")
    try:
        os.ftruncate(fd, 5 << 20)
        peaks = memory.stop()  # sooner than the sampler's next read of the shared memory (every 200 ms)
    finally:
        os.close(fd)
    assert peaks["shared"] >= 5 << 20
    assert peaks["peak"] >= 5 << 20


def test_between_turns_the_sampler_reads_once_a_second_before_either_side_writes(
        monkeypatch: pytest.MonkeyPatch) -> None:
    moments: list[tuple[int, bool]] = []
    sample = ServerMemory._sample_once

    def recorded(self: ServerMemory, shared_too: bool) -> None:
        moments.append((time.monotonic_ns(), shared_too))
        sample(self, shared_too)

    monkeypatch.setattr(ServerMemory, "_sample_once", recorded)
    memory = ServerMemory(os.getpid(), between_turns=True)
    time.sleep(2.3)
    memory.stop()
    between = moments[1:-1]  # the first and the last come at its start and its stop, whenever they are
    assert len(between) >= 2, moments
    for ns, shared_too in between:
        assert shared_too and QUIET_AT_NS <= ns % 1_000_000_000 < turns.SKIP_NS, moments
