"""Component-reported outcomes: ``report(name, value)`` over gRPC and in process.

What a component reports is kept by the server under the component's own id (from its token) as
count, sum, min, max and last, exactly; a refused report (empty or over-long name, a value that is
not a finite number, one name too many) raises the named error and records nothing. Read back from
the metrics snapshot, from ``cast stats --json`` and from each server of a two-server system.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path
from typing import Any

import grpc
import pytest

import cast
from cast.auth import TokenSigner
from cast.core.policies import make_policy
from cast.core.records import Identity, Limits
from cast.core.reports import MAX_REPORT_NAMES
from cast.server.wire import wire_system
from cast.v1 import inspection_pb2, inspection_pb2_grpc
from tests.client.conftest import ThreadServer
from tests.conftest import SECRET, VENV_BIN, ServerHandle
from tests.orchestrator.conftest import start_cast_run, write_config


def without_time(reports: dict[str, Any]) -> dict[str, Any]:
    """Reports by component and name without ``last_time`` (a clock reading, never asserted)."""
    return {cid: {name: {k: v for k, v in r.items() if k != "last_time"} for name, r in named.items()}
            for cid, named in reports.items()}


def test_reports_are_kept_per_component_and_name_exactly(make_component: Any) -> None:
    quizzer = make_component(cast.UnmanagedComponent, "quizzer", "language")
    other = make_component(cast.UnmanagedComponent, "other", "vision")
    for correct in (1, 0, 1, 1):
        quizzer.report("answers_correct", correct)
    quizzer.report("answer_time_s", 0.5)
    quizzer.report("answer_time_s", 0.25)
    quizzer.report("answer_time_s", -1.5)  # any finite number: a signed measure too
    other.report("answers_correct", 7)
    reports = make_component.system.metrics.snapshot()["reports"]
    assert without_time(reports) == {
        "other": {"answers_correct": {"count": 1, "sum": 7.0, "min": 7.0, "max": 7.0, "last": 7.0, "mean": 7.0}},
        "quizzer": {
            "answer_time_s": {"count": 3, "sum": -0.75, "min": -1.5, "max": 0.5, "last": -1.5, "mean": -0.25},
            "answers_correct": {"count": 4, "sum": 3.0, "min": 0.0, "max": 1.0, "last": 1.0, "mean": 0.75},
        },
    }
    assert reports["quizzer"]["answer_time_s"]["last_time"] > 0


@pytest.mark.parametrize(("name", "value", "words"), [
    ("", 1, "a report name must be 1 to 128 bytes"),
    ("é" * 65, 1, "a report name must be 1 to 128 bytes"),  # 130 bytes of UTF-8 in 65 characters
    ("score", math.nan, "report 'score': the value must be a finite number, got nan"),
    ("score", math.inf, "report 'score': the value must be a finite number, got inf"),
    ("score", -math.inf, "report 'score': the value must be a finite number, got -inf"),
    ("score", "many", "report 'score': the value must be a number, got 'many'"),
])
def test_a_bad_report_is_invalid_argument_and_records_nothing(make_component: Any, name: str, value: Any,
                                                                words: str) -> None:
    quizzer = make_component(cast.UnmanagedComponent, "quizzer", "language")
    with pytest.raises(cast.InvalidArgumentError) as refused:
        quizzer.report(name, value)
    assert words in str(refused.value)
    assert make_component.system.metrics.snapshot()["reports"] == {}


def test_a_name_past_the_limit_is_resource_exhausted_and_records_nothing(make_component: Any) -> None:
    quizzer = make_component(cast.UnmanagedComponent, "quizzer", "language")
    for i in range(MAX_REPORT_NAMES):
        quizzer.report(f"m{i}", i)
    with pytest.raises(cast.ResourceExhaustedError) as refused:
        quizzer.report("one-too-many", 1)
    assert f"component 'quizzer' already reports {MAX_REPORT_NAMES} names, the limit" in str(refused.value)
    quizzer.report("m3", 10)  # a name it has is still taken
    other = make_component(cast.UnmanagedComponent, "other", "vision")
    other.report("one-too-many", 1)  # the limit is per component
    mine = make_component.system.metrics.snapshot()["reports"]["quizzer"]
    assert len(mine) == MAX_REPORT_NAMES and "one-too-many" not in mine
    assert (mine["m3"]["count"], mine["m3"]["sum"], mine["m3"]["last"]) == (2, 13.0, 10.0)


def test_the_reporter_is_the_tokens_component_and_a_report_needs_a_token() -> None:
    system = wire_system("t", ["vision"], policies={"vision": make_policy("always", {})}, limits=Limits())
    server = ThreadServer(system)
    try:
        assert server.running is not None
        with grpc.insecure_channel(server.running.endpoint) as channel:
            stub = inspection_pb2_grpc.InspectionStub(channel)
            token = server.signer.issue(Identity("quizzer", "vision", False))
            stub.Report(inspection_pb2.ReportRequest(name="answers_correct", value=1),
                        metadata=(("authorization", f"Bearer {token}"),))
            with pytest.raises(grpc.RpcError) as refused:
                stub.Report(inspection_pb2.ReportRequest(name="answers_correct", value=1))
            assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
        assert list(system.metrics.snapshot()["reports"]) == ["quizzer"]
        assert system.metrics.snapshot()["reports"]["quizzer"]["answers_correct"]["count"] == 1
    finally:
        server.stop()


def stats_json(endpoint: str, secret: str) -> dict[str, Any]:
    """`cast stats --json` of the system at ``endpoint``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    out = subprocess.run([str(VENV_BIN / "cast"), "stats", "--json", "--endpoint", endpoint],
                         env={**env, "CAST_SECRET": secret}, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    doc: dict[str, Any] = json.loads(out.stdout)
    return doc


def test_a_script_reports_and_cast_stats_shows_it(server: ServerHandle) -> None:
    with cast.connect(server.endpoint, server.token("notebook", "vision")) as wm:
        for seconds in (2.0, 0.5, 1.25):
            wm.report("answer_time_s", seconds)
    reports = stats_json(server.endpoint, SECRET)["reports"]
    assert without_time(reports) == {"notebook": {"answer_time_s": {
        "count": 3, "sum": 3.75, "min": 0.5, "max": 2.0, "last": 1.25, "mean": 1.25}}}


def test_a_component_reports_to_its_own_sas_server_and_cast_stats_merges_the_servers(tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "two.yaml", {
        "system": "two",
        "subarchitectures": {"vision": {"components": {}}, "motor": {"components": {}}},
        "servers": {"main": {"subarchitectures": ["vision"]}, "motion": {"subarchitectures": ["motor"]}},
    })
    run = start_cast_run(tmp_path, cfg)
    try:
        secret = (run.runtime_dir / "secret").read_text().strip()
        for who, sa in (("mover", "motor"), ("looker", "vision")):
            with cast.connect(runtime_dir=run.runtime_dir, component_id=who, subarchitecture=sa) as wm:
                wm.report("done", 1)
        servers = run.state()["servers"]
        tool = TokenSigner(secret.encode()).issue(Identity("tool", "", False))
        per_server = {}
        for name in ("main", "motion"):
            with grpc.insecure_channel(servers[name]["endpoint"]) as channel:
                reply = inspection_pb2_grpc.InspectionStub(channel).GetMetrics(
                    inspection_pb2.GetMetricsRequest(), metadata=(("authorization", f"Bearer {tool}"),))
            per_server[name] = sorted(r.component for r in reply.reports)
        assert per_server == {"main": ["looker"], "motion": ["mover"]}
        merged = stats_json(run.state()["endpoint"], secret)
        assert merged["servers"] == 2
        assert {cid: named["done"]["count"] for cid, named in merged["reports"].items()} == {"looker": 1, "mover": 1}
    finally:
        assert run.stop() == 0, run.output()
