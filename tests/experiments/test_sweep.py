"""`cast sweep`: every combination runs as a fresh `cast run`; results, report and plots; failures and Ctrl-C."""

from __future__ import annotations

import json
import signal
import subprocess
import textwrap
from pathlib import Path

import pytest

from cast.errors import InvalidArgumentError
from cast.experiments.plan import Variant, parse_axes, variants
from tests.conftest import ROOT, wait_for
from tests.orchestrator.conftest import CAST, COMPONENTS

PNG = b"\x89PNG\r\n\x1a\n"


def sweep(*args: str, cwd: Path = ROOT, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([CAST, "sweep", *args], capture_output=True, text=True, cwd=cwd, timeout=timeout)


def test_two_layouts_twice_give_every_run_a_report_and_plots(tmp_path: Path) -> None:
    out = tmp_path / "out"
    done = sweep("configs/pipeline.yaml", "--vary", "LAYOUT=one-sa,three-sa", "--policy", "main=fifo,priority",
                 "--for", "1", "--repeat", "2", "-o", str(out))
    # main exists only in one-sa: refused before any run
    assert done.returncode == 2 and "has no SA 'main'" in done.stderr, done.stderr
    assert not (out / "results.json").exists()

    done = sweep("configs/pipeline.yaml", "--vary", "LAYOUT=one-sa,three-sa", "--for", "1", "--repeat", "2",
                 "-o", str(out))
    assert done.returncode == 0, done.stdout + done.stderr
    results = json.loads((out / "results.json").read_text())
    assert [(r["variant"], r["repeat"], r["ok"]) for r in results["runs"]] == [
        ("LAYOUT=one-sa", 1, True), ("LAYOUT=three-sa", 1, True), ("LAYOUT=one-sa", 2, True),
        ("LAYOUT=three-sa", 2, True)]
    assert results["machine"]["cpus"] and results["planned_runs"] == 4 and not results["interrupted"]
    # Each run is a fresh system of its layout: one SA, or three.
    sas = {r["variant"]: sorted(sa["name"] for sa in r["summary"]["subarchitectures"]) for r in results["runs"]}
    assert sas == {"LAYOUT=one-sa": ["main"], "LAYOUT=three-sa": ["reasoning", "reporting", "sensing"]}
    report = (out / "report.md").read_text()
    for variant in ("LAYOUT=one-sa", "LAYOUT=three-sa"):
        row = next(line for line in report.splitlines() if line.startswith(f"| `{variant}`"))
        assert "| 2/2 |" in row and "| 4 |" in row, row  # both runs ok; the 4 items completed as tasks
        assert row.count("n/a") == 0, row  # the servers' metrics give latency and task wait
    plots = sorted(out.glob("*.png"))
    assert plots and all(p.read_bytes().startswith(PNG) and p.stat().st_size > 2000 for p in plots), plots
    names = {p.name for p in plots}
    assert {"events_per_s.png", "latency_p50_ms.png", "task_wait_ms.png", "traffic-LAYOUT=one-sa.png",
            "traffic-LAYOUT=three-sa.png"} <= names, names
    assert "![events_per_s.png](events_per_s.png)" in report


def test_a_policy_is_varied_through_an_overlay_and_the_file_is_untouched(tmp_path: Path) -> None:
    before = (ROOT / "configs" / "pipeline" / "three-sa.yaml").read_text()
    done = sweep("configs/pipeline.yaml", "--policy", "reasoning=fifo,priority", "--for", "1", "-o", str(tmp_path))
    assert done.returncode == 0, done.stdout + done.stderr
    runs = json.loads((tmp_path / "results.json").read_text())["runs"]
    policies = {r["variant"]: next(sa["policy"] for sa in r["summary"]["subarchitectures"]
                                   if sa["name"] == "reasoning") for r in runs}
    assert policies == {"reasoning:fifo": "fifo(max_concurrent=1)", "reasoning:priority": "priority(max_concurrent=1)"}
    assert (ROOT / "configs" / "pipeline" / "three-sa.yaml").read_text() == before


def _config_with_a_failing_variant(tmp_path: Path) -> Path:
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent(f"""\
        system: failing-sweep
        variables: {{KIND: Producer}}
        python_path: [{COMPONENTS}]
        subarchitectures:
          work:
            components:
              one: {{class: "orch_components:${{KIND}}", restart: never}}
        """))
    return path


def test_a_failed_run_is_reported_and_the_sweep_goes_on(tmp_path: Path) -> None:
    config = _config_with_a_failing_variant(tmp_path)
    done = sweep(str(config), "--vary", "KIND=Failing,Producer", "--for", "1", "-o", str(tmp_path / "out"),
                 cwd=tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    runs = json.loads((tmp_path / "out" / "results.json").read_text())["runs"]
    assert [(r["variant"], r["ok"]) for r in runs] == [("KIND=Failing", False), ("KIND=Producer", True)]
    assert runs[0]["error"].startswith("one crashed 1 time(s) (exit codes 1) (its output: "), runs[0]["error"]
    log = Path(runs[0]["error"].rsplit("its output: ", 1)[1].rstrip(")"))
    assert "broken on purpose" in log.read_text()
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Failed runs" in report and "`KIND=Failing` repeat 1" in report
    assert next(line for line in report.splitlines() if line.startswith("| `KIND=Failing`")).count("n/a") >= 3


def test_ctrl_c_keeps_the_runs_that_finished(tmp_path: Path) -> None:
    config = _config_with_a_failing_variant(tmp_path)
    out = tmp_path / "out"
    proc = subprocess.Popen([CAST, "sweep", str(config), "--for", "2", "--repeat", "20", "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)

    def finished() -> int:
        try:
            return len(json.loads((out / "results.json").read_text())["runs"])
        except (OSError, ValueError):
            return 0

    wait_for(lambda: finished() >= 1, timeout=120, what="a finished run")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    results = json.loads((out / "results.json").read_text())
    assert results["interrupted"] and 1 <= len(results["runs"]) < 20
    assert all(r["ok"] for r in results["runs"])  # the run cut short is not kept as a failure
    assert f"{len(results['runs'])} of 20 runs made (interrupted)" in (out / "report.md").read_text()


def test_bad_options_name_the_problem_and_run_nothing(tmp_path: Path) -> None:
    for args, message in [
        (["--vary", "LAYOUT"], "--vary 'LAYOUT': write NAME=value1,value2"),
        (["--vary", "LAYOUT=a,a"], "a value is listed twice"),
        (["--vary", "LAYOUT=nope"], "variant LAYOUT=nope: the configuration has errors"),
        (["--repeat", "0"], "--repeat 0: give at least 1"),
    ]:
        done = sweep("configs/pipeline.yaml", *args, "--for", "1", "-o", str(tmp_path / "out"))
        assert done.returncode == 2 and message in done.stderr, (args, done.stderr)
    assert not (tmp_path / "out").exists()


def test_variants_are_every_combination_with_the_first_axis_slowest() -> None:
    vary = parse_axes(["A=1,2", "B=x,y"], "--vary")
    found = variants(vary, parse_axes(["sa=fifo,priority"], "--policy"))
    assert [v.name for v in found][:3] == ["A=1,B=x,sa:fifo", "A=1,B=x,sa:priority", "A=1,B=y,sa:fifo"]
    assert len(found) == 8 and Variant().name == "default"
    with pytest.raises(InvalidArgumentError, match="given twice"):
        parse_axes(["A=1", "A=2"], "--vary")


@pytest.mark.parametrize("layout", ["one", "two", "three"])
def test_the_shipped_experiment_is_valid_in_every_layout(layout: str) -> None:
    for policy in ("fifo", "priority"):
        done = subprocess.run([CAST, "check", "configs/experiments/decomposition.yaml", "--set", f"SAS={layout}",
                               "--set", f"VISION_POLICY={policy}"], capture_output=True, text=True, cwd=ROOT)
        assert done.returncode == 0, done.stderr
        assert f"system 'decomposition-{layout}': {dict(one=1, two=2, three=3)[layout]} subarchitecture" in done.stdout


def test_reported_outcomes_are_summed_and_averaged_per_run() -> None:
    from cast.experiments.measures import reports

    summary = {"metrics": {"reports": {
        "a": {"answers": {"count": 2, "sum": 2.0}, "time_s": {"count": 2, "sum": 3.0}},
        "b": {"answers": {"count": 1, "sum": 1.0}},
    }}}
    assert reports(summary) == {"answers sum": 3.0, "answers mean": 1.0, "time_s sum": 3.0, "time_s mean": 1.5}
    assert reports({}) == {}


def test_a_spread_keeps_three_significant_digits_of_small_values() -> None:
    from cast.experiments.measures import spread

    small = spread([0.0123, 0.0131, 0.0119])
    assert small is not None and small.text() == "0.0123 [0.0119, 0.0131]"
    assert spread([1234.4, 1200.0]).text() == "1217 [1200, 1234]"  # type: ignore[union-attr]
    assert spread([4.0, 4.0]).text(0) == "4" and spread([None]) is None  # type: ignore[union-attr]
