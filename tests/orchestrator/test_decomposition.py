"""The same components under two decompositions (one SA, three SAs), chosen by a variable."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.conftest import ROOT
from tests.orchestrator.conftest import start_cast_run, wait_for

PIPELINE = ROOT / "configs" / "pipeline.yaml"
STRING, INT, BOOL = ("google.protobuf.StringValue", "google.protobuf.Int64Value", "google.protobuf.BoolValue")
ITEMS = {(f"item-{i}", STRING, "producer") for i in range(4)}
RESULTS = {(f"result-{i}", INT, "worker") for i in range(4)}
REPORT = {("report", BOOL, "reporter")}


def contents(entries: list[dict[str, Any]]) -> dict[str, set[tuple[str, str, str]]]:
    """SA -> {(id, type, author)}, leaving out the task manager's own task entries."""
    out: dict[str, set[tuple[str, str, str]]] = {}
    for e in entries:
        if e["type"] != "cast.v1.Task":
            out.setdefault(e["subarchitecture"], set()).add((e["id"], e["type"], e["author"]))
    return out


@pytest.mark.parametrize(
    ("layout", "expected"),
    [
        ("three-sa", {"sensing": ITEMS, "reasoning": RESULTS, "reporting": REPORT}),
        ("one-sa", {"main": ITEMS | RESULTS | REPORT}),
    ],
)
def test_pipeline_gives_the_same_results_in_both_decompositions(
    tmp_path: Path, layout: str, expected: dict[str, set[tuple[str, str, str]]]
) -> None:
    run = start_cast_run(tmp_path, PIPELINE, "--set", f"LAYOUT={layout}")
    try:
        reporting = "reporting" if layout == "three-sa" else "main"
        wait_for(lambda: any(e["id"] == "report" for e in run.cli_json("ls", reporting)), what="the report")
        assert contents(run.cli_json("ls")) == expected
        desc = run.cli_json("components")
        assert {c["id"]: c["subarchitecture"] for c in desc} == {
            "producer": "sensing" if layout == "three-sa" else "main",
            "worker": "reasoning" if layout == "three-sa" else "main",
            "reporter": reporting,
        }
        assert run.state()["system"] == f"pipeline-{layout}"
    finally:
        code = run.stop()
    assert code == 0, run.output()
    assert "every component ran and stopped cleanly" in run.output()
