"""A sweep's plots as PNG files, with matplotlib (no display needed).

One bar chart per measure that some run has (median per variant, the error bar
spanning the smallest to the largest repeat), and one cross-SA traffic heat map
per variant (the median over its repeats of reads + writes from components of
the row's SA into the column's WM).
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

from cast.errors import InvalidArgumentError
from cast.experiments.measures import MEASURES, traffic
from cast.experiments.report import VariantResult

__all__ = ["write_plots"]


def _pyplot() -> ModuleType:
    try:
        import matplotlib
    except ImportError as exc:
        raise InvalidArgumentError("cast sweep draws its plots with matplotlib, which is not installed: "
                                   "pip install 'cast-grpc[experiments]' (or matplotlib), or give --no-plots") from exc
    matplotlib.use("Agg")  # files only: no display on a robot or in CI
    import matplotlib.pyplot as plt
    return plt


def write_plots(results: Sequence[VariantResult], out: Path) -> list[str]:
    """Write the PNGs into ``out``; their file names, in the order the report shows them."""
    plt = _pyplot()
    written: list[str] = []
    names = [r.variant.name for r in results]
    for measure in MEASURES:
        values = [r.values[measure.key] for r in results]
        if all(v is None for v in values):
            continue
        fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(names) + 2), 3.6))
        medians = [v.median if v else 0.0 for v in values]
        below = [v.median - v.low if v else 0.0 for v in values]
        above = [v.high - v.median if v else 0.0 for v in values]
        ax.bar(range(len(names)), medians, yerr=[below, above], capsize=4, color="#4c72b0")
        ax.set_xticks(range(len(names)), names, rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(f"{measure.title} ({measure.unit})")
        ax.set_title(f"{measure.title}: median and range over repeats", fontsize=10)
        fig.tight_layout()
        name = f"{measure.key}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(name)
    for result in results:
        name = _heat_map(plt, result, out)
        if name:
            written.append(name)
    return written


def _heat_map(plt: ModuleType, result: VariantResult, out: Path) -> str:
    """The variant's traffic matrix as a heat map; "" if its runs have none."""
    matrices = [traffic(r.summary) for r in result.runs if r.ok and r.summary is not None]
    matrices = [m for m in matrices if m]
    if not matrices:
        return ""
    sas = sorted({sa for m in matrices for pair in m for sa in pair})
    grid = [[statistics.median(m.get((a, b), 0.0) for m in matrices) for b in sas] for a in sas]
    fig, ax = plt.subplots(figsize=(1.1 * len(sas) + 2.5, 1.0 * len(sas) + 1.8))
    image = ax.imshow(grid, cmap="viridis")
    ax.set_xticks(range(len(sas)), sas, rotation=30, ha="right")
    ax.set_yticks(range(len(sas)), sas)
    ax.set_xlabel("into the WM of")
    ax.set_ylabel("from components of")
    for i, row in enumerate(grid):
        for j, value in enumerate(row):
            ax.text(j, i, f"{value:.0f}", ha="center", va="center", color="white" if value < max(map(max, grid)) / 2
                    else "black", fontsize=8)
    fig.colorbar(image, ax=ax, label="reads + writes (median over repeats)")
    ax.set_title(f"cross-SA traffic: {result.variant.name}", fontsize=9)
    fig.tight_layout()
    name = f"traffic-{result.variant.slug}.png"
    fig.savefig(out / name, dpi=110)
    plt.close(fig)
    return name
