"""The benchmark code that needs no server: delivery figures, row building and target checks."""

from __future__ import annotations

import copy
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import pytest

from bench.delivery_stats import parse_watcher, totals, watcher_figures
from bench.many_components import split
from bench.peer_fanout import END, WARM, Receiver, frame
from bench.report import plot_panels
from bench.rows import Results, rows
from bench.rows_calls import m1_row, m1p_row, m3_row
from bench.rows_scale import m8_misses, m8_row, m8_rss_bound, m9_misses, m9_row
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


def test_receiver_stamps_data_and_ends_at_end(capsys: pytest.CaptureFixture[str]) -> None:
    r = Receiver()
    r.on_message(frame(WARM, 16))
    r.on_message(frame(WARM, 16))
    r.on_message(frame(7, 1000))
    assert not r.done.is_set()
    r.on_message(frame(END, 16))
    assert r.done.is_set() and list(r.stamps) == [7] and r.bytes == 1000
    assert capsys.readouterr().out == "ready\n"  # once


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


def _watchers(p99: float = 10_000.0, lost: int = 0) -> dict[str, Any]:
    one = {"p50_us": 5000.0, "p99_us": p99, "lost": lost, "skipped": 0, "mb_per_s": 30.0, "received": 60}
    return {label: dict(one) for label in ("Python 1", "C++", "Java", "Python 2")}


def _m8() -> dict[str, Any]:
    phase = {"watchers": _watchers(), "total": {"mb_per_s": 200.0, "bytes": 1}, "server_rss_peak": 150 << 20,
             "missing": {}}
    peer = {"watchers": {"subscriber 1": _watchers()["C++"]}, "total": {"mb_per_s": 500.0, "bytes": 1}}
    return {"size": 1 << 20, "hz": 30, "history_bytes": 64 << 20, "server_rss_idle": 70 << 20,
            "floor": [{"mb_per_s": 300.0, "p50_us": 3000.0}],
            **{f"cast_{d}_{p}": copy.deepcopy(phase) for d in ("queue", "latest") for p in ("hz", "b2b")},
            **{f"{n}_{p}": copy.deepcopy(peer) for n in ("zenoh", "redis") for p in ("hz", "b2b")}}


def test_m8_targets() -> None:
    assert m8_misses(_m8()) == [] and m8_row(_m8())["met"]
    slow = _m8()
    slow["cast_latest_hz"]["watchers"]["Java"]["p99_us"] = 20_001.0
    assert [m for m in m8_misses(slow) if "Java p99" in m]
    lost = _m8()
    lost["cast_queue_b2b"]["watchers"]["C++"]["lost"] = 1
    assert m8_misses(lost) == ["queue b2b: C++ lost 1"]
    thin = _m8()
    thin["cast_queue_b2b"]["total"]["mb_per_s"] = 149.0  # < 0.5 x 300
    assert len(m8_misses(thin)) == 1
    fat = _m8()
    fat["cast_latest_b2b"]["server_rss_peak"] = m8_rss_bound(fat) + 1
    assert "server RSS peak" in m8_misses(fat)[0]
    assert not m8_row({"error": "C++ not built"})["met"]


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
