"""Metrics from real processes: `cast serve --metrics` and `cast run --metrics` in Prometheus's text format
(parsed with prometheus_client's parser), `cast stats` (tables and --json), `--summary-json`'s metrics,
`--no-metrics`; servers and endpoints on port 0 only."""

from __future__ import annotations

import json
import os
import re
import subprocess
import urllib.request
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter
from prometheus_client.parser import text_string_to_metric_families

import cast
from tests.conftest import SECRET, VENV_BIN, ServerHandle, start_server, wait_for
from tests.orchestrator.conftest import COMPONENTS, start_cast_run, write_config

N_ADDS, N_READS = 6, 3


def scrape(address: str) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    """``http://ADDRESS/metrics`` parsed: sample name -> sorted labels -> value."""
    with urllib.request.urlopen(f"http://{address}/metrics", timeout=10) as reply:
        text = reply.read().decode()
    samples: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
    for family in text_string_to_metric_families(text):
        assert family.name.startswith("cast_"), family.name
        for sample in family.samples:
            samples.setdefault(sample.name, {})[tuple(sorted(sample.labels.items()))] = sample.value
    return samples


def value(samples: dict[str, Any], name: str, **labels: str) -> float:
    """One sample's value (0 if the series is absent)."""
    return float(samples.get(name, {}).get(tuple(sorted(labels.items())), 0.0))


def stats(server: ServerHandle, *extra: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    return subprocess.run([str(VENV_BIN / "cast"), "stats", "--endpoint", server.endpoint, *extra],
                          env={**env, "CAST_SECRET": SECRET}, capture_output=True, text=True, timeout=60)


def metrics_address(lines: list[str]) -> str:
    """The address a server or `cast run` printed for its /metrics."""
    for line in lines:
        found = re.search(r"metrics on http://(\S+)/metrics", line)
        if found:
            return found.group(1)
    raise AssertionError(f"no metrics address in {lines}")


def known_traffic(server: ServerHandle) -> None:
    """N adds from a component of vision into language, M reads by one of language, a watcher in motor."""
    writer = server.connect("writer", "vision", privileged=True)
    reader = server.connect("reader", "language")
    watcher = server.connect("watcher", "motor")
    seen: list[Any] = []
    try:
        watcher.on_change(cast.global_type_filter(Counter), seen.append)
        for i in range(N_ADDS):
            writer.add(f"c{i}", Counter(writer="writer", value=i), subarchitecture="language")
        for i in range(N_READS):
            reader.get(f"c{i}", Counter)
        wait_for(lambda: len(seen) == N_ADDS, what="every event")
    finally:
        for c in (writer, reader, watcher):
            c._cast_close()


def test_cast_serve_serves_exact_counts_in_prometheus_text_and_cast_stats(tmp_path: Path) -> None:
    server = start_server(tmp_path, {"system": "prom", "subarchitectures": {"vision": {}, "language": {}, "motor": {}}},
                          ["--metrics", "127.0.0.1:0"])
    try:
        address = metrics_address(wait_for(lambda: [ln for ln in server.log_lines if "metrics on" in ln],
                                           what="the metrics line"))
        assert not address.endswith(":0")
        known_traffic(server)
        m = scrape(address)
        assert value(m, "cast_metrics_enabled", system="prom") == 1
        assert value(m, "cast_traffic_writes_total", from_sa="vision", to_sa="language") == N_ADDS
        assert value(m, "cast_traffic_reads_total", from_sa="language", to_sa="language") == N_READS
        assert value(m, "cast_traffic_events_total", from_sa="motor", to_sa="language") == N_ADDS
        assert value(m, "cast_component_writes_total", component="writer", subarchitecture="vision",
                     operation="add") == N_ADDS
        assert value(m, "cast_component_reads_total", component="reader", subarchitecture="language") == N_READS
        assert value(m, "cast_wm_writes_total", subarchitecture="language", operation="add") == N_ADDS
        assert value(m, "cast_wm_writes_total", subarchitecture="vision", operation="add") == 0
        # The watcher's latency histogram: every event in it, buckets cumulative up to +Inf.
        labels = {"component": "watcher", "subarchitecture": "motor"}
        assert value(m, "cast_event_delivery_latency_seconds_count", **labels) == N_ADDS
        assert value(m, "cast_event_delivery_latency_seconds_bucket", le="+Inf", **labels) == N_ADDS
        # The same counts through Inspection.GetMetrics, merged by cast stats.
        out = stats(server, "--json")
        assert out.returncode == 0, out.stderr
        doc = json.loads(out.stdout)
        assert doc["system"] == "prom" and doc["servers"] == 1 and doc["enabled"] is True
        assert doc["components"]["writer"]["adds"] == N_ADDS and doc["components"]["reader"]["reads"] == N_READS
        cells = {(c["from_sa"], c["to_sa"]): c for c in doc["traffic"]}
        assert cells[("vision", "language")]["writes"] == N_ADDS and cells[("motor", "language")]["events"] == N_ADDS
        assert doc["delivery_latency"]["watchers"]["watcher"]["count"] == N_ADDS
        table = stats(server)
        assert table.returncode == 0, table.stderr
        assert "traffic" in table.stdout and re.search(r"writer\s*│\s*vision", table.stdout), table.stdout
    finally:
        server.stop()


def test_a_server_with_no_metrics_counts_nothing(tmp_path: Path) -> None:
    server = start_server(tmp_path, {"system": "off", "subarchitectures": {"vision": {}, "language": {}, "motor": {}}},
                          ["--metrics", "127.0.0.1:0", "--no-metrics"])
    try:
        address = metrics_address(wait_for(lambda: [ln for ln in server.log_lines if "metrics on" in ln],
                                           what="the metrics line"))
        known_traffic(server)
        m = scrape(address)
        assert value(m, "cast_metrics_enabled", system="off") == 0
        assert "cast_traffic_writes_total" not in m
        doc = json.loads(stats(server, "--json").stdout)
        assert doc["enabled"] is False and doc["components"] == {} and doc["traffic"] == []
    finally:
        server.stop()


def test_cast_run_serves_metrics_and_writes_them_into_its_summary(tmp_path: Path) -> None:
    config = write_config(tmp_path / "system.yaml", {
        "system": "counted",
        "subarchitectures": {
            "a": {"components": {"writer": {"class": "barrier_components:BarrierWriter", "privileged": True,
                                            "args": {"sa": "b", "count": N_ADDS}}}},
            "b": {"components": {"watch": {"class": "barrier_components:BarrierWatcher"}}},
        },
    })
    assert COMPONENTS.is_dir()
    summary = tmp_path / "summary.json"
    run = start_cast_run(tmp_path, config, "--metrics", "127.0.0.1:0", "--summary-json", str(summary))
    try:
        address = metrics_address(run.lines)
        # The writer adds N entries and an -end entry into b; the watcher then adds its report.
        wait_for(lambda: any(e["id"] == "seen-watch-writer" for e in run.cli_json("ls", "b")), what="the report")
        m = scrape(address)
        assert value(m, "cast_traffic_writes_total", from_sa="a", to_sa="b") == N_ADDS + 1
        assert value(m, "cast_traffic_writes_total", from_sa="b", to_sa="b") == 1
        assert value(m, "cast_component_writes_total", component="writer", subarchitecture="a",
                     operation="add") == N_ADDS + 1
        assert value(m, "cast_event_delivery_latency_seconds_count", component="watch",
                     subarchitecture="b") >= N_ADDS + 1
        live = run.cli_json("stats")
        assert {(c["from_sa"], c["to_sa"]): c["writes"] for c in live["traffic"] if c["from_sa"]} == {
            ("a", "b"): N_ADDS + 1, ("b", "b"): 1}
        # The tools' reads count too, under their own caller (no SA): `cast ls b` listed b above.
        tools = {c["to_sa"]: c for c in live["traffic"] if not c["from_sa"]}
        assert tools["b"]["reads"] >= 1 and tools["b"]["writes"] == 0, live["traffic"]
    finally:
        assert run.stop() == 0, run.output()
    counted = json.loads(summary.read_text())["metrics"]
    assert counted["system"] == "counted" and counted["servers"] == 1
    assert {(c["from_sa"], c["to_sa"]): c["writes"] for c in counted["traffic"] if c["from_sa"]} == {
        ("a", "b"): N_ADDS + 1, ("b", "b"): 1}
    assert counted["components"]["writer"]["bytes_in"] == live["components"]["writer"]["bytes_in"]
    assert set(counted) == set(live)  # the summary's metrics are cast stats --json
