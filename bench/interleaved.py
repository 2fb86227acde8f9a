"""`python -m bench.interleaved VAR [--frames N] [--rounds R]`: A and B of a change to M8's path, in the same rounds.

The machines this project is measured on change speed by up to 2 x from one
15-second round to the next, for every process at once
(docs/performance-m8.md, "A and B in the same round"). That is more than
most changes to the path are worth, so rounds of A alternating with rounds
of B cannot tell the two apart. Here both sides run in every round, a second
each in turn:

- every process of M8's 1 MiB 30 Hz phase (``cast serve``, the C++ writer,
  the four watchers) has ``VAR=alternate`` in its environment;
- the code under test (a local patch, never committed) takes its B path
  while :func:`b_side` is true, its A path otherwise:
  ``os.environ.get(VAR) == "alternate" and time.monotonic_ns() // 10**9 % 2 == 1``
  in Python, the same test on ``CLOCK_MONOTONIC`` in C++ and Java;
- each frame counts for the side of the second in which its writer stamped
  it, on the same clock. The frames of the first :data:`SKIP_NS` of each second
  are left out: the side changes at a frame, so the frame in flight when it
  changes is partly A and partly B.

Both sides then share the machine's state to within a second. With nothing
reading VAR they measure the same thing, and their difference is the
method's spread ("A/A": within about 25 µs of each watcher's p50, either
way, pooled over six rounds, on the machine of that section).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Mapping

from bench import images
from bench.cast_cases import Server
from bench.delivery_stats import latencies_us, ordinal, settling
from bench.harness import scratch
from bench.other_clients import cpp_command

__all__ = ["SKIP_NS", "b_side", "main", "split"]

SKIP_NS = 70_000_000
"""Frames stamped this early in a second are left out (two frames at 30 Hz: the one the side changed in, and margin)."""

_SECOND = 1_000_000_000


def _in_b(ns: int) -> bool:
    """Whether CLOCK_MONOTONIC time ``ns`` falls in a B second (an odd one)."""
    return ns // _SECOND % 2 == 1


def b_side(var: str, now_ns: int | None = None) -> bool:
    """Whether code reading ``var`` should take its B path now (the odd seconds of CLOCK_MONOTONIC)."""
    if os.environ.get(var) != "alternate":
        return False
    return _in_b(time.monotonic_ns() if now_ns is None else now_ns)


def split(sent: Mapping[int, int], stamps: Mapping[str, Mapping[int, int]],
          frames: int) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """The latencies (µs) of the last ``frames`` writes, each watcher's, on side A and on side B.

    ``sent``: revision -> the writer's stamp (ns); ``stamps``: label -> revision ->
    the watcher's stamp (ns). A write goes to the side of its stamp's second; one
    stamped in the first :data:`SKIP_NS` of a second is left out, and a watcher
    that has no stamp for a write has no latency for it.
    """
    sides: tuple[dict[int, int], dict[int, int]] = ({}, {})
    for revision in sorted(sent)[-frames:] if frames > 0 else ():
        t0 = sent[revision]
        if t0 % _SECOND >= SKIP_NS:
            sides[_in_b(t0)][revision] = t0
    a, b = ({label: latencies_us(side, got) for label, got in stamps.items()} for side in sides)
    return a, b


def _p50s(side: Mapping[str, list[float]]) -> list[int]:
    """Each of M8's watchers' p50 on one side; -1 for one with no frame there (or that did not run)."""
    return [round(statistics.median(side[label])) if side.get(label) else -1 for label in images.WATCHERS]


def main(argv: list[str] | None = None) -> int:
    """Run the rounds; print each round's p50s on both sides, then both sides pooled over the rounds."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.interleaved",
        description="A and B of a change to M8's path in the same rounds: every process of M8's 1 MiB 30 Hz phase "
                    "gets VAR=alternate, the change (a local patch) takes its B path in the odd seconds of "
                    "CLOCK_MONOTONIC (bench.interleaved.b_side), and each frame counts for the side of its "
                    "writer's stamp. docs/performance.md, \"Writes on a stream, pipelining, image-sized entries, "
                    "many components\".")
    parser.add_argument("var", help="the environment variable the code under test reads")
    parser.add_argument("--frames", type=int, default=600, help="measured frames per round (default 600: 20 s)")
    parser.add_argument("--rounds", type=int, default=6, help="rounds, each on a new server (default 6)")
    args = parser.parse_args(argv)
    writer = cpp_command()
    if isinstance(writer, str):
        parser.error(writer)
    os.environ[args.var] = "alternate"
    commands = [(label, images._watcher_command(label, "queue")) for label in images.WATCHERS]
    pooled: tuple[dict[str, list[float]], dict[str, list[float]]] = (
        {label: [] for label in images.WATCHERS}, {label: [] for label in images.WATCHERS})
    kept = args.frames - settling(args.frames)  # as M8's figures count them
    print(f"p50 in µs, {' / '.join(images.WATCHERS)}; A: even seconds, B: odd ({args.var}=alternate)", flush=True)
    with scratch("interleaved") as work:
        for number in range(1, args.rounds + 1):
            server = Server(work / f"round-{number}", [images.SA], limits={"history_bytes": images.HISTORY_BYTES})
            try:
                run_ = images.record_phase(server, writer, commands, images.SIZE, args.frames,
                                           1 / images.HZ, f"i{number}", images.WARM_PER_FRAME * args.frames)
            finally:
                server.stop()
            sides = split(run_.sent, {label: got["stamps"] for label, got in run_.got.items()}, kept)
            for into, side in zip(pooled, sides, strict=True):
                for label in images.WATCHERS:
                    into[label].extend(side.get(label, []))
            a, b = (_p50s(side) for side in sides)
            print(f"{ordinal(number)} round: A {a} (slowest {max(a)}), B {b} (slowest {max(b)}), "
                  f"{time.strftime('%H:%M:%S')}", flush=True)
    a, b = (_p50s(side) for side in pooled)
    difference = [y - x for x, y in zip(a, b, strict=True)]
    print(f"pooled: A {a} (slowest {max(a)}), B {b} (slowest {max(b)}); B - A {difference}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
