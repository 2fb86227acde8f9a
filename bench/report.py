"""Writing bench/results/latest.{md,json} and the PNG plots from one run's figures."""

from __future__ import annotations

import json
import platform
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def _ratio(value: float, base: float | None) -> str:
    if not base or base != base:  # missing or NaN
        return "-"
    return f"{value / base:.2f}x"


def write_markdown(path: Path, rows: list[dict[str, Any]], machine: dict[str, Any], command: str) -> None:
    """The table: every figure, its ratio to the floor and to the peer, target and whether it was met."""
    lines = [
        "# Benchmark results",
        "",
        f"Command: `{command}`. Machine: {machine['cores']} cores, {machine['python']}, grpcio {machine['grpcio']}, "
        f"protobuf {machine['protobuf']}, Redis {machine['redis']}, {machine['platform']}, "
        f"CPU idle: {machine.get('idle', 'unknown')}; cast package: {machine.get('build', 'unknown')}.",
        "",
        "| id | figure | value | floor | vs floor | peer | vs peer | target | met |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        for i, fig in enumerate(row["figures"]):
            lines.append(
                "| {id} | {name} | {value} | {floor} | {vf} | {peer} | {vp} | {target} | {met} |".format(
                    id=row["id"] if i == 0 else "",
                    name=fig["name"],
                    value=fig["value"],
                    floor=fig.get("floor", "-"),
                    vf=_ratio(fig["value"], fig.get("floor")),
                    peer=fig.get("peer", "-"),
                    vp=_ratio(fig["value"], fig.get("peer")),
                    target=row["target"] if i == 0 else "",
                    met=("yes" if row["met"] else "**no**") if i == 0 else "",
                )
            )
    notes = [f"- {row['id']}: {row['note']}" for row in rows if row.get("note")]
    if notes:
        lines += ["", "Notes:", "", *notes]
    lines += ["", "Floors and peer measured in the same run:", ""]
    for key, value in machine["floors"].items():
        lines.append(f"- {key}: {value}")
    path.write_text("\n".join(lines) + "\n")


def write_json(path: Path, rows: list[dict[str, Any]], machine: dict[str, Any]) -> None:
    """One object per id with its figures, target and whether it was met."""
    doc = {"machine": machine, "results": {row["id"]: {k: v for k, v in row.items() if k != "id"} for row in rows}}
    path.write_text(json.dumps(doc, indent=2) + "\n")


def plot_latency_cdf(path: Path, series: dict[str, list[float]]) -> None:
    """CDF of write -> event latency (and the floors', where given)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, samples in series.items():
        xs = sorted(samples)
        ys = [(i + 1) / len(xs) for i in range(len(xs))]
        ax.plot(xs, ys, label=label)
    ax.set_xscale("log")
    ax.set_xlabel("latency (µs, log scale)")
    ax.set_ylabel("fraction of events")
    ax.set_title("Write → event latency")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_xy(path: Path, xs: Sequence[float], ys: Sequence[float], xlabel: str, ylabel: str, title: str) -> None:
    """A simple line plot with points."""
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(xs, ys, marker="o")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_panels(path: Path, xs: Sequence[float], panels: dict[str, dict[str, Sequence[float]]], xlabel: str,
                title: str, log_y: Sequence[str] = ()) -> None:
    """One panel per title (its y label), each with one or more named series over the same xs (log x).

    Panels named in ``log_y`` get a log y axis too (latencies that grow by orders of magnitude).
    """
    fig, axes = plt.subplots(2, (len(panels) + 1) // 2, figsize=(10, 7), squeeze=False)
    for ax, (ylabel, series) in zip(axes.flat, panels.items(), strict=False):
        for label, ys in series.items():
            ax.plot(xs, ys, marker="o", label=label)
        ax.set_xscale("log")
        if ylabel in log_y:
            ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        if len(series) > 1:
            ax.legend()
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


_QOS_NONE_US = 2_000_000_000  # the kernel's PM QoS default: no CPU latency limit


def cpu_idle(cpus: Path = Path("/sys/devices/system/cpu"), haltpoll: Path = Path("/sys/module/haltpoll/parameters"),
             qos: Path = Path("/dev/cpu_dma_latency")) -> str:
    """How this machine's CPUs idle, which the latencies of paced phases (M3, M8) depend on.

    At 30 Hz every process sleeps between frames, so each frame wakes idle
    CPUs, and what that costs is the machine's: the cpuidle driver and CPU
    0's idle states with their exit latencies, the guest halt-polling window
    when a VM's haltpoll driver runs (0: an idle CPU halts at once and is woken
    by the host), and the PM QoS CPU latency limit where it can be read (root;
    a process holding ``/dev/cpu_dma_latency`` at 0 keeps idle CPUs polling).
    docs/performance.md, "Idle CPUs and latency". What cannot be read is left out.
    """
    parts = []
    driver = _read(cpus / "cpuidle" / "current_driver")
    if driver:
        states = []
        for state in sorted((cpus / "cpu0" / "cpuidle").glob("state*"), key=lambda p: int(p.name[5:] or 0)):
            name, latency = _read(state / "name"), _read(state / "latency")
            if name:
                states.append(f"{name} {latency} µs" if latency else name)
        parts.append(f"{driver} ({', '.join(states)})" if states else driver)
        poll_ns = _read(haltpoll / "guest_halt_poll_ns") if driver == "haltpoll" else ""
        if poll_ns:
            parts.append(f"halt polling {poll_ns} ns")
    try:
        with open(qos, "rb") as f:
            limit = int.from_bytes(f.read(4), "little", signed=True)
        parts.append("CPU latency limit " + ("none" if limit >= _QOS_NONE_US else f"{limit} µs"))
    except OSError:
        pass
    return "; ".join(parts) or "unknown"


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return ""


def machine_info(floors: dict[str, Any], redis_version: str) -> dict[str, Any]:
    """Cores, versions and how the CPUs idle, and the floors for the report header."""
    import os

    import google.protobuf
    import grpc

    return {
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "grpcio": grpc.__version__,
        "protobuf": google.protobuf.__version__,
        "redis": redis_version,
        "platform": platform.platform(),
        "idle": cpu_idle(),
        "build": package_build(),
        "floors": floors,
    }


def package_build() -> str:
    """Which build of the cast package this process runs: compiled by mypyc (make mypyc) or the sources."""
    import cast.core.host

    origin = cast.core.host.__file__ or ""
    return "compiled (mypyc)" if origin.endswith(".so") else "pure Python"
