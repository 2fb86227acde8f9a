"""Large values by shared memory against bytes through gRPC and against Zenoh, in one run.

A Python writer (bench/image_writer.py) overwrites a 1 MiB and then a 6 MiB
entry, at 30 Hz and back to back, and four Python watchers
(bench/image_watcher.py) read every byte of every value through its view; first with the server's shared
memory turned off (``cast serve --no-shared-memory``: every value as bytes in
gRPC messages), then on (the writer stages each value, the watchers are lent
it). Zenoh (bench/zenoh_peer.py: a Python publisher, four Python subscribers)
carries the same values in the same run. Figures per phase: the watchers'
p50 and p99 latency (write start -> callback; the first tenth of the frames
left out), the frames lost, and the MB/s delivered to the four together.

``python -m bench.shared_memory [FRAMES] [--language python|cpp|java]`` (default 150 per phase): with
``--language java`` the writer and the four watchers are the Java client's (``cast.bench.Bench
image-write`` and ``image-watch``), with ``--language cpp`` the C++ client's (``cast_bench
image-write`` and ``image-watch``, M8's writer). Each watcher, in every language, reads every byte
of each value through its view (a checksum, checked against what the writer wrote) before it stamps it.
M8 in ``make bench`` (bench/images.py) is the judged comparison; this is the standalone one of the
bytes path (``--no-shared-memory``) against the shared one.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench import zenoh_peer
from bench.cast_cases import Server
from bench.checksum import expected_cast
from bench.delivery_stats import parse_watcher, settling, totals, watcher_figures
from bench.harness import PYTHON, ROOT, child_env
from bench.other_clients import cpp_command, java_command

__all__ = ["run"]

SA = "images"
WATCHERS = 4
HZ = 30
SIZES = (1 << 20, 6 << 20)
HISTORY_BYTES = 64 << 20


def _commands(language: str) -> tuple[list[str], list[str]]:
    """The writer's and a watcher's command line (before their arguments) in ``language``."""
    if language == "python":
        return [PYTHON, "-m", "bench.image_writer"], [PYTHON, "-m", "bench.image_watcher"]
    command = java_command() if language == "java" else cpp_command()
    if isinstance(command, str):
        raise RuntimeError(command)
    return [*command, "image-write"], [*command, "image-watch"]


def _check_sums(sent: dict[int, int], got: list[dict[str, Any]], docs: list[dict[str, Any]], size: int) -> None:
    """Each watcher read every byte of what it received: its checksum is the writer's values' (bench.checksum)."""
    for g, doc in zip(got, docs, strict=True):
        want = expected_cast(sent, g["stamps"], size)
        if int(doc["checksum"]) != want:
            raise RuntimeError(f"a watcher's checksum is {doc['checksum']}, not {want}: it read other bytes")


def _phase(server: Server, tag: str, size: int, frames: int, gap_s: float, language: str = "python") -> dict[str, Any]:
    writer, watcher = _commands(language)
    watchers = []
    for i in range(WATCHERS):
        env = child_env(server.env(f"{tag}-w{i}", SA))
        watchers.append(subprocess.Popen([*watcher, "queue"], env=env, cwd=ROOT,
                                         stdout=subprocess.PIPE, stderr=tempfile.TemporaryFile("w+"), text=True))
    try:
        for proc in watchers:
            assert proc.stdout is not None
            if proc.stdout.readline().strip() != "ready":
                raise RuntimeError("a watcher did not start")
        env = child_env(server.env(f"{tag}-writer", SA))
        out = subprocess.run([*writer, str(size), str(frames), str(round(gap_s * 1e6))],
                             env=env, cwd=ROOT, capture_output=True, text=True, timeout=600)
        if out.returncode != 0:
            raise RuntimeError(f"the writer failed: {out.stderr[-800:]}")
        sent = {int(k): int(v) for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()}
        docs = []
        for proc in watchers:
            text, _ = proc.communicate(timeout=120)
            docs.append(json.loads([x for x in text.splitlines() if x.startswith("{")][-1]))
        got = [parse_watcher(doc) for doc in docs]
    finally:
        for proc in watchers:
            if proc.poll() is None:
                proc.kill()
    _check_sums(sent, got, docs, size)
    figures = _figures(sent, got, extra=2)
    if "shared" in docs[0]:
        figures["by_shared_memory"] = [int(doc["shared"]) for doc in docs]
    return figures


def _figures(sent: dict[int, int], got: list[dict[str, Any]], extra: int) -> dict[str, Any]:
    late = dict(sorted(sent.items())[settling(len(sent)):])
    per = []
    for g in got:
        whole, steady = watcher_figures(sent, g, extra), watcher_figures(late, g, extra)
        per.append({**whole, "p50_us": steady["p50_us"], "p99_us": steady["p99_us"]})
    return {"watchers": per, "total": totals(sent, got)}


def run(workdir: Path, frames: int, language: str = "python") -> dict[str, Any]:
    """Every phase (CAST's writer and watchers in ``language``); raw figures."""
    out: dict[str, Any] = {}
    for name, args in (("bytes", ("--no-shared-memory",)), ("shared", ())):
        server = Server(workdir / name, [SA], limits={"history_bytes": HISTORY_BYTES}, serve_args=args)
        try:
            for size in SIZES:
                for pace, gap in (("30 Hz", 1 / HZ), ("back to back", 0.0)):
                    key = f"{name} {size >> 20} MiB {pace}"
                    print(f"running {key}", file=sys.stderr, flush=True)
                    out[key] = _phase(server, f"{name}{size}{pace[0]}", size, frames, gap, language)
        finally:
            server.stop()
    for size in SIZES:
        for pace, gap in (("30 Hz", 1 / HZ), ("back to back", 0.0)):
            key = f"zenoh {size >> 20} MiB {pace}"
            print(f"running {key}", file=sys.stderr, flush=True)
            run_ = zenoh_peer.large(frames, gap, size)
            out[key] = _figures(run_["sent"], run_["watchers"], extra=0)
    return out


def table(results: dict[str, Any]) -> str:
    """The figures as Markdown."""
    lines = ["| path | p50 ms (4 watchers) | p99 ms (4 watchers) | lost | MB/s to the four |", "|---|---|---|---|---|"]
    for key, r in results.items():
        p50 = "/".join(f"{w['p50_us'] / 1000:.1f}" for w in r["watchers"])
        p99 = "/".join(f"{w['p99_us'] / 1000:.1f}" for w in r["watchers"])
        lost = sum(w["lost"] for w in r["watchers"])
        lines.append(f"| {key} | {p50} | {p99} | {lost} | {r['total']['mb_per_s']:,.0f} |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    """``[FRAMES] [--language python|cpp|java]``: every phase, then the figures as JSON and as a table."""
    parser = argparse.ArgumentParser(prog="python -m bench.shared_memory")
    parser.add_argument("frames", nargs="?", type=int, default=150)
    parser.add_argument("--language", choices=("python", "cpp", "java"), default="python",
                        help="the language of CAST's writer and watchers")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        results = run(Path(tmp), args.frames, args.language)
    print(json.dumps(results))
    print(table(results))


if __name__ == "__main__":
    main(sys.argv[1:])
