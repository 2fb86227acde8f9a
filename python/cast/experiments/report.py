"""A sweep's report: one row per variant with the median and spread of each measure, as Markdown."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from cast.experiments.measures import MEASURES, Measure, Spread, reports, spread
from cast.experiments.plan import Variant
from cast.experiments.sweep import RunRecord, Sweep, machine_facts

__all__ = ["VariantResult", "render_report", "summarise"]


@dataclass(frozen=True)
class VariantResult:
    """A variant's runs and each measure's spread over the ones that succeeded."""

    variant: Variant
    runs: list[RunRecord]
    values: dict[str, Spread | None]
    outcomes: dict[str, Spread | None]

    @property
    def ok(self) -> int:
        """How many of its runs succeeded."""
        return sum(1 for r in self.runs if r.ok)


def summarise(sweep: Sweep) -> list[VariantResult]:
    """Each variant's measures over its successful runs, in the sweep's order."""
    out: list[VariantResult] = []
    for variant in sweep.variants:
        runs = [r for r in sweep.runs if r.variant == variant]
        good = [r for r in runs if r.ok and r.summary is not None]
        values = {m.key: spread(m.read(r.summary, sweep.seconds) for r in good if r.summary is not None)
                  for m in MEASURES}
        names = sorted({n for r in good if r.summary is not None for n in reports(r.summary)})
        outcomes = {n: spread(reports(r.summary).get(n) for r in good if r.summary is not None) for n in names}
        out.append(VariantResult(variant, runs, values, outcomes))
    return out


def _cell(value: Spread | None, measure: Measure | None = None) -> str:
    if value is None:
        return "n/a"
    return value.text(0 if measure is not None and measure.unit == "tasks" else None)


def render_report(sweep: Sweep, results: Sequence[VariantResult], command: str, plots: Sequence[str]) -> str:
    """The report as Markdown: settings, the table, reported outcomes, failed runs, plots."""
    facts = machine_facts()
    made, failed = len(sweep.runs), sum(1 for r in sweep.runs if not r.ok)
    lines = [
        f"# Sweep of `{sweep.config}`",
        "",
        f"`{command}`",
        "",
        f"{made} of {sweep.total} runs made{' (interrupted)' if sweep.interrupted else ''}, {failed} failed; "
        f"each `cast run --for {sweep.seconds:g}`, {sweep.repeat} repeat(s) per variant, seed {sweep.seed}. "
        f"Machine: {facts.get('cpus')} CPUs, {facts.get('platform')}, Python {facts.get('python')}"
        + (f", commit {facts['git_commit']}" if "git_commit" in facts else "") + ".",
        "",
        "Each cell: the median over the variant's successful runs, [smallest, largest] when they differ; "
        "n/a where no run had the measure (docs/experiments.md explains each).",
        "",
    ]
    header = ["variant", "runs ok", *(f"{m.title} ({m.unit})" for m in MEASURES)]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for res in results:
        row = [f"`{res.variant.name}`", f"{res.ok}/{len(res.runs)}",
               *(_cell(res.values[m.key], m) for m in MEASURES)]
        lines.append("| " + " | ".join(row) + " |")
    names = sorted({n for res in results for n in res.outcomes})
    if names:
        lines += ["", "## Reported outcomes", "",
                  "What the components of a run reported (`report(name, value)`): per name the sum over the "
                  "run and the mean of the values; each cell the median over the variant's runs.", "",
                  "| variant | " + " | ".join(names) + " |", "|" + "---|" * (len(names) + 1)]
        for res in results:
            lines.append(f"| `{res.variant.name}` | " + " | ".join(_cell(res.outcomes.get(n)) for n in names) + " |")
    bad = [r for r in sweep.runs if not r.ok]
    if bad:
        lines += ["", "## Failed runs", ""]
        lines += [f"- `{r.variant.name}` repeat {r.repeat}: exit {r.exit_code}: {r.error}" for r in bad]
    if plots:
        lines += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"
