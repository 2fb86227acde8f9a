"""M8's C++ writer (``cast_bench image-write``) against a real server: the parts of its run, as bench.images
reads them."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

from bench.cast_cases import Server
from bench.images import HISTORY_BYTES, SA, WARM_SIZE, _write
from tests.interop.cpp_support import cpp_executable

MS = 1_000_000


def test_the_warm_up_goes_in_bursts_with_a_pause_after_each_but_the_last(tmp_path: Path) -> None:
    # 2 cold values, 7 warm-up values in bursts of 3 with 200 ms pauses (3 | 3 | 1), 2 measured ones back to back.
    server = Server(tmp_path, [SA], limits={"history_bytes": HISTORY_BYTES})
    try:
        command = [str(cpp_executable("cast_bench")), "image-write", str(WARM_SIZE), "2", "0",
                   "7", str(WARM_SIZE), "2", "3", "200000"]
        sent = _write(server, command, "burst")
    finally:
        server.stop()
    stamps = [sent[k] for k in sorted(sent)]
    assert len(stamps) == 2 + 7 + 2  # every overwrite stamped, in revision order
    warm = stamps[2:9]
    gaps = [b - a for a, b in pairwise(warm)]
    # A pause after the third and the sixth, of at least 200 ms; nowhere else (within a burst, back to back).
    assert gaps[2] >= 200 * MS and gaps[5] >= 200 * MS, gaps
    assert max(gap for i, gap in enumerate(gaps) if i not in (2, 5)) < min(gaps[2], gaps[5]), gaps
