"""Another host on this machine for M8's remote watcher: a network namespace joined to this one by a veth pair.

The benchmark runs as root (as the multi-host tests do, tests/netns.py). The
namespace has its own loopback and its own abstract Unix socket namespace, so
a CAST client in it cannot reach the server's shared-memory socket and gets
large values as bytes, as a client on another machine does. Its traffic goes
only over the pair, between this machine's two namespaces.
"""

from __future__ import annotations

import os
import subprocess
from types import TracebackType

__all__ = ["OtherHost"]


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()} (M8's remote watcher needs a "
                           "network namespace: run the benchmark as root on Linux)")


class OtherHost:
    """A network namespace and a veth pair to it: :attr:`address` here (for the server), :attr:`prefix` to run in it."""

    def __init__(self) -> None:
        tag = os.getpid() % 100_000
        self.ns = f"castm8{tag}"
        self._here = f"vm8{tag}a"
        subnet = f"10.217.{tag % 250}"
        self.address = f"{subnet}.1"  # this namespace's end, where the server listens
        self.prefix = ["ip", "netns", "exec", self.ns]
        self._made: list[str] = []
        try:
            _ip("netns", "add", self.ns)
            self._made.append("ns")
            _ip("-n", self.ns, "link", "set", "lo", "up")
            _ip("link", "add", self._here, "type", "veth", "peer", "name", f"vm8{tag}b")
            self._made.append("link")
            _ip("link", "set", f"vm8{tag}b", "netns", self.ns)
            _ip("addr", "add", f"{self.address}/24", "dev", self._here)
            _ip("link", "set", self._here, "up")
            _ip("-n", self.ns, "addr", "add", f"{subnet}.2/24", "dev", f"vm8{tag}b")
            _ip("-n", self.ns, "link", "set", f"vm8{tag}b", "up")
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Delete the pair and the namespace."""
        if "link" in self._made:
            subprocess.run(["ip", "link", "del", self._here], capture_output=True)
        if "ns" in self._made:
            subprocess.run(["ip", "netns", "del", self.ns], capture_output=True)
        self._made.clear()

    def __enter__(self) -> OtherHost:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()
