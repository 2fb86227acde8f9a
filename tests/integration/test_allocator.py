"""The server's fixed mmap threshold: freed large values go back to the system (cast.server.allocator)."""

from __future__ import annotations

import subprocess
import sys

PROGRAM = """
import sys
from cast.server.allocator import return_large_blocks

def rss_mib():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 // (1 << 20)

if sys.argv[1] == "fixed":
    assert return_large_blocks()
x = bytes(1 << 20); del x  # freeing one mapped block is what makes glibc raise its threshold
base = rss_mib()
images = [bytes([i]) * (1 << 20) for i in range(64)]
newest = images[-1]
del images  # every image but the newest is freed, as the history drops old revisions
print(rss_mib() - base)
"""


def _growth(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", PROGRAM, mode], capture_output=True, text=True, check=True)
    return int(out.stdout)


def test_freed_images_are_returned_with_the_fixed_threshold_and_kept_without_it() -> None:
    assert _growth("default") >= 48  # glibc keeps the freed MiBs in its heap (what bench M8 saw)
    assert _growth("fixed") <= 8
