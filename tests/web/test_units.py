"""The web view's plain parts: rates from counter samples, the login key, and where the package sits."""

from __future__ import annotations

import ast
import re
from typing import Any

import pytest

from cast.core.metrics_view import empty_snapshot
from cast.web.access import Access
from cast.web.rates import RateWindow, Sample
from tests.conftest import ROOT

BOUNDS = (0.001, 0.01, 0.1)


def metrics(latency: list[int], traffic: list[dict[str, Any]]) -> dict[str, Any]:
    snap = empty_snapshot("s", BOUNDS)
    snap["delivery_latency"]["all"]["buckets"] = latency
    snap["traffic"] = traffic
    return snap


def cell(from_sa: str, to_sa: str, reads: int, writes: int, events: int) -> dict[str, Any]:
    return {"from_sa": from_sa, "to_sa": to_sa, "reads": reads, "writes": writes, "events": events,
            "bytes_in": 0, "bytes_out": 0}


def test_rates_come_from_the_growth_between_samples() -> None:
    window = RateWindow()
    window.add(Sample(100.0, {"a": 10, "b": 0}, metrics([0, 0, 0, 0], [cell("b", "a", 0, 0, 0)])))
    window.add(Sample(102.0, {"a": 30, "b": 4}, metrics([4, 0, 0, 0], [cell("b", "a", 10, 2, 6),
                                                                        cell("", "a", 50, 0, 0),
                                                                        cell("a", "a", 8, 8, 0)])))
    window.add(Sample(103.0, {"a": 30, "b": 4}, metrics([4, 0, 0, 0], [cell("b", "a", 10, 2, 6),
                                                                        cell("", "a", 50, 0, 0),
                                                                        cell("a", "a", 8, 8, 0)])))
    assert window.events_per_s() == {"a": [[-1.0, 10.0], [0.0, 0.0]], "b": [[-1.0, 2.0], [0.0, 0.0]]}
    first, second = window.latency()
    assert first["count"] == 4 and 0 < first["p50_s"] <= 0.001 and first["p90_s"] <= 0.001
    assert second == {"t": 0.0, "count": 0, "p50_s": None, "p90_s": None}  # nothing delivered: no quantile
    # Over the 3 s since the first sample (less than the window of 5 s): tools (no SA) and traffic inside an SA are
    # not arrows.
    (arrow,) = window.traffic()
    assert (arrow["from"], arrow["to"]) == ("b", "a")
    assert arrow["reads_per_s"] == pytest.approx(10 / 3) and arrow["writes_per_s"] == pytest.approx(2 / 3)
    assert arrow["events_per_s"] == pytest.approx(2.0) and arrow["reads"] == 10
    assert window.within()["a"]["writes_per_s"] == pytest.approx(8 / 3)


def test_a_server_that_restarted_counts_no_negative_rate_and_old_samples_go() -> None:
    window = RateWindow(window_s=10)
    for i, rev in enumerate((50, 60, 5, 9)):  # the server restarted between the 2nd and 3rd sample
        window.add(Sample(float(i), {"a": rev}, metrics([rev, 0, 0, 0], [cell("b", "a", rev, 0, 0)])))
    assert [rate for _t, rate in window.events_per_s()["a"]] == [10.0, 0.0, 4.0]
    assert all(p["count"] >= 0 for p in window.latency())
    for i in range(4, 30):
        window.add(Sample(float(i), {"a": 9}, metrics([9, 0, 0, 0], [])))
    assert len(window.events_per_s()["a"]) <= 10


def test_the_login_key_is_spent_by_its_first_use_and_a_new_one_is_announced() -> None:
    announced: list[str] = []
    access = Access(lambda token: token == "good", announced.append)
    access.base_url = "http://127.0.0.1:1"
    first = access.login_link()
    key = first.split("key=")[1]
    session = access.spend_key(key)
    assert session is not None and access.session_ok(session)
    assert access.spend_key(key) is None and access.spend_key("") is None
    assert announced == [access.login_link()] and announced[0] != first
    assert access.session_for_token("bad") is None and access.session_for_token("good") is not None
    assert not access.session_ok("made-up") and not access.session_ok(None)


# What the web view may not import: it is a tool on the public API, below the orchestrator (which runs it inside
# `cast run`) and the command line (docs/design.md, "Folders").
ABOVE = ("cast.orchestrator", "cast.cli", "cast.config", "cast.agent", "cast.server.app", "cast.server.working_memory")


def test_the_web_view_imports_nothing_above_it() -> None:
    offending = []
    for path in sorted((ROOT / "python" / "cast" / "web").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
            offending += [f"{path.name}: {n}" for n in names if any(n == b or n.startswith(b + ".") for b in ABOVE)]
    assert not offending


def test_every_file_the_page_loads_is_package_data() -> None:
    static = ROOT / "python" / "cast" / "web" / "static"
    assert '"web/static/*"' in (ROOT / "pyproject.toml").read_text()
    wanted = set(re.findall(r'/static/([\w.]+)', (static / "index.html").read_text()))
    for script in static.glob("*.js"):
        wanted |= set(re.findall(r'from "\./([\w.]+)"', script.read_text()))
    assert wanted and all((static / name).is_file() for name in wanted), wanted
