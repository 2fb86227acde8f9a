"""CAST measurements M1-M6 (M7, the C++ and Java clients, is in bench/other_clients.py)."""

from __future__ import annotations

import itertools
import json
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil
import yaml
from google.protobuf.wrappers_pb2 import BytesValue, StringValue

import cast
from bench import turns
from bench.floors import GAP_S, EchoFloor
from bench.harness import PYTHON, child_env, latencies_us, percentile, rate, start, summary_us
from cast.auth import TokenSigner
from cast.client.component import Component
from cast.client.grpc_transport import GrpcTransport
from cast.client.local_transport import LocalTransport
from cast.core.records import Identity
from cast.core.system import System

SECRET = "bench-secret-0123456789abcdef0123456789"
VALUE = BytesValue(value=b"x" * 100)


class Server:
    """`cast serve` on a free port, as users run it."""

    def __init__(
        self,
        workdir: Path,
        sas: list[str],
        limits: dict[str, int] | None = None,
        persistence: dict[str, str] | None = None,
        serve_args: tuple[str, ...] = (),
        listen: str = "127.0.0.1:0",
    ) -> None:
        workdir.mkdir(parents=True, exist_ok=True)
        config: dict[str, Any] = {"system": "bench", "subarchitectures": {sa: {} for sa in sas}}
        if limits:
            config["limits"] = limits
        if persistence:
            config["persistence"] = persistence
        path = workdir / "bench.yaml"
        path.write_text(yaml.safe_dump(config, sort_keys=False))
        self.proc = start(
            [str(Path(PYTHON).parent / "cast"), "serve", str(path), "--listen", listen, *serve_args],
            cwd=workdir,
            env={"CAST_SECRET": SECRET},
        )
        self.endpoint = self.proc.first_line.removeprefix("listening on ")
        self.signer = TokenSigner(SECRET.encode())

    def component(self, component_id: str, sa: str, cls: type[Component] = cast.UnmanagedComponent) -> Any:
        """A component in this process, bound over gRPC."""
        identity = Identity(component_id, sa)
        c = cls()
        c._cast_bind(GrpcTransport(self.endpoint, self.signer.issue(identity), identity))
        return c

    def env(self, component_id: str, sa: str) -> dict[str, str]:
        """Launch environment for a component process."""
        identity = Identity(component_id, sa)
        return {
            "CAST_ENDPOINT": self.endpoint,
            "CAST_COMPONENT_ID": component_id,
            "CAST_SUBARCHITECTURE": sa,
            "CAST_TOKEN": self.signer.issue(identity),
            "CAST_ARGS": "{}",
        }

    def rss_bytes(self) -> int:
        """Resident memory of the server process."""
        return int(psutil.Process(self.proc.process.pid).memory_info().rss)

    def stop(self) -> None:
        """Stop the server."""
        self.proc.stop()


def _after_floor_block(echo: EchoFloor, items: list[str], op: Callable[[str], object]) -> tuple[float, float]:
    """One interleaved pair: seconds of ``len(items)`` echo calls, then seconds of ``op`` over ``items``."""
    floor = echo.block_seconds(len(items))
    t0 = time.perf_counter()
    for item in items:
        op(item)
    return floor, time.perf_counter() - t0


def m2_batch(server: Server, batches: int) -> dict[str, Any]:
    """M2: Batch of 100 adds."""
    c = server.component("m2", "bench")
    counter = iter(range(10**9))

    def one(_: int) -> None:
        c.batch([("add", f"m2-{next(counter)}", VALUE) for _ in range(100)])

    per_s = rate(batches, one)
    c._cast_close()
    return {"entries_per_s": round(per_s * 100), "batches_per_s": round(per_s)}


LATENCY_WATCHER = r"""
import json, sys, threading, time, cast
from cast.client.runner import LaunchContract
n = int(sys.argv[1])
c = cast.UnmanagedComponent()
c._cast_bind(LaunchContract.from_env().connect())
stamps = {}
done = threading.Event()
def cb(ch):
    stamps[ch.revision] = time.perf_counter()
    if len(stamps) >= n:
        done.set()
c.on_change(cast.address_filter("lat"), cb)
print("ready", flush=True)
done.wait(120)
print(json.dumps(stamps), flush=True)
"""


def m3_latency(server: Server, n: int, gap_s: float = GAP_S, sa: str = "bench", turn: int = turns.NONE,
               sides: int = 2) -> dict[str, Any]:
    """M3: write -> event latency from a writer (this process) to a watcher in its own process.

    Writes are spaced by ``gap_s`` so each sample sees an idle system; both
    processes stamp with CLOCK_MONOTONIC (time.perf_counter), which is shared
    by all processes of a Linux machine. With a ``turn`` of ``sides``
    (:mod:`bench.turns`), each write waits for its turn: M7 takes the three
    languages' latencies so, each in its own SA.
    """
    env = child_env(server.env(f"m3-watcher-{sa}", sa))
    watcher = subprocess.Popen([PYTHON, "-c", LATENCY_WATCHER, str(n)], env=env, stdout=subprocess.PIPE, text=True)
    assert watcher.stdout is not None
    assert watcher.stdout.readline().strip() == "ready"
    writer = server.component(f"m3-writer-{sa}", sa)
    sent: dict[int, float] = {}
    first = writer.add("lat", VALUE).revision
    for _ in range(n - 1):
        time.sleep(gap_s)
        if turn:
            turns.wait_for_turn(turn, sides)
        t0 = time.perf_counter()
        sent[writer.overwrite("lat", VALUE).revision] = t0
    out, _ = watcher.communicate(timeout=120)
    writer.delete("lat")  # so that another run on this server (M7's) can add it again
    writer._cast_close()
    arrived = {int(k): v for k, v in json.loads(out.strip().splitlines()[-1]).items()}
    samples = [(arrived[r] - t0) * 1e6 for r, t0 in sent.items() if r in arrived and r != first]
    lost = len(sent) - len(samples)
    warm = min(50, len(samples) // 10)
    samples = samples[warm:]
    return {**summary_us(samples), "lost": lost, "samples_us": samples}


FANOUT_WATCHER = r"""
import json, sys, threading, time, cast
from cast.client.runner import LaunchContract
from google.protobuf.wrappers_pb2 import BytesValue
n_watchers, expected = int(sys.argv[1]), int(sys.argv[2])
base = LaunchContract.from_env()
tokens = json.loads(sys.argv[3])  # one per watcher: each is its own component
done = threading.Event()
results = []
for w in range(n_watchers):
    contract = LaunchContract(base.endpoint, f"{base.component_id}-{w}", base.subarchitecture, tokens[w], {})
    c = cast.UnmanagedComponent()
    c._cast_bind(contract.connect())
    state = {"count": 0, "last": 0, "out_of_order": 0, "duplicates": 0, "end": 0.0}
    def cb(ch, state=state):
        if ch.revision <= state["last"]:
            state["out_of_order" if ch.revision < state["last"] else "duplicates"] += 1
        state["last"] = ch.revision
        state["count"] += 1
        if state["count"] == expected:
            state["end"] = time.time()
    c.on_change(cast.local_type_filter(BytesValue), cb)
    results.append(state)
print("ready", flush=True)
deadline = time.time() + 120
while time.time() < deadline and any(s["count"] < expected for s in results):
    time.sleep(0.01)
print(json.dumps(results), flush=True)
"""


_FANOUT_RUNS = itertools.count()


def m4_fanout(server: Server, events: int, watchers: int = 16, processes: int = 4) -> dict[str, Any]:
    """M4: one writer, 16 watchers (in 4 processes) each receiving every event."""
    per_proc = watchers // processes
    procs = []
    for p in range(processes):
        env = child_env(server.env(f"fan{p}", "fanout"))
        # Tokens name the component (the server checks them at Register): one per watcher of the process.
        tokens = [server.signer.issue(Identity(f"fan{p}-{w}", "fanout")) for w in range(per_proc)]
        proc = subprocess.Popen(
            [PYTHON, "-c", FANOUT_WATCHER, str(per_proc), str(events), json.dumps(tokens)], env=env,
            stdout=subprocess.PIPE, text=True,
        )
        procs.append(proc)
    for proc in procs:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
    writer = server.component("fan-writer", "fanout")
    run = next(_FANOUT_RUNS)  # the scaling runs share one server: fresh ids for each
    start_t = time.time()
    for b in range(0, events, 100):
        writer.batch([("add", f"f{run}-{i}", VALUE) for i in range(b, min(events, b + 100))])
    write_end = time.time()
    states = []
    for proc in procs:
        out, _ = proc.communicate(timeout=180)
        states.extend(json.loads(out.strip().splitlines()[-1]))
    writer._cast_close()
    delivered = sum(s["count"] for s in states)
    end = max(s["end"] for s in states) if all(s["end"] for s in states) else time.time()
    return {
        "watchers": watchers,
        "events_written": events,
        "delivered": delivered,
        "lost": watchers * events - delivered,
        "out_of_order": sum(s["out_of_order"] for s in states),
        "duplicates": sum(s["duplicates"] for s in states),
        "delivered_per_s": round(delivered / (end - start_t)),
        "write_s": round(write_end - start_t, 3),
    }


def m5_in_process(n: int, block: int = 100) -> dict[str, Any]:
    """M5: an in-process component: add -> its own callback, and get.

    add -> callback is measured back to back in blocks of ``block`` samples, each
    after a block of the same thread handoff without the write: a callback that
    only stamps, submitted straight to the component's dispatcher thread. Both
    use the same two threads, so they share the machine's placement of them (on
    one CPU or two; see docs/performance.md, M5), and the difference is the cost
    of the write and its event.
    """
    system = System("bench", ["bench"])
    c = cast.UnmanagedComponent()
    c._cast_bind(LocalTransport(system, Identity("m5", "bench")))
    arrived = threading.Event()
    stamp = [0.0]

    def arrive() -> None:
        stamp[0] = time.perf_counter()
        arrived.set()

    c.on_change(cast.local_type_filter(StringValue), lambda change: arrive())
    counter = iter(range(10**9))
    value = StringValue(value="x" * 100)

    def until_callback(begin: Callable[[], object]) -> float:
        arrived.clear()
        t0 = time.perf_counter()
        begin()
        arrived.wait(10)
        return stamp[0] - t0

    def handoff() -> float:
        return until_callback(lambda: c._dispatcher.submit(arrive))

    def add_to_callback() -> float:
        return until_callback(lambda: c.add(f"e{next(counter)}", value))

    for _ in range(block):  # warm-up
        handoff()
        add_to_callback()
    floor: list[float] = []
    add_lat: list[float] = []
    for _ in range(max(1, n // block)):
        floor += [handoff() * 1e6 for _ in range(block)]
        add_lat += [add_to_callback() * 1e6 for _ in range(block)]

    def get(i: int) -> float:
        t0 = time.perf_counter()
        c.get("e1", StringValue)
        return time.perf_counter() - t0

    get_lat = latencies_us(n, get)
    c._cast_close()
    return {"add_to_callback": summary_us(add_lat), "handoff": summary_us(floor), "get": summary_us(get_lat)}


def m6_large(workdir: Path, checkpoints: list[int], probe: int, echo: EchoFloor, block: int = 100) -> dict[str, Any]:
    """M6: many 100-byte entries in one WM: add rate at each checkpoint size, memory and type read at the end.

    The probe at each size is made of blocks of adds alternating with blocks of
    echo-floor calls, and the rates compared across sizes are each relative to the
    floor measured with them: the fill takes long enough for the machine's speed
    to drift between the first checkpoint and the last.
    """
    server = Server(workdir, ["big"])
    try:
        c = server.component("m6", "big")
        for i in range(10):
            c.add(f"ten-{i}", StringValue(value="needle"))
        done = 10
        rates: dict[int, float] = {}
        relative: dict[int, float] = {}  # add rate / echo floor rate, measured together
        blocks = max(1, probe // block)
        counter = iter(range(10**9))
        for size in checkpoints:
            while done < size:
                step = min(1000, size - done)
                c.batch([("add", f"bulk-{done + j}", VALUE) for j in range(step)])
                done += step
            for _ in range(block):  # warm-up after the bulk load
                c.add(f"probe-{next(counter)}", VALUE)
            ours = floor = 0.0
            for _ in range(blocks):
                ids = [f"probe-{next(counter)}" for _ in range(block)]
                pair = _after_floor_block(echo, ids, lambda entry_id: c.add(entry_id, VALUE))
                floor, ours = floor + pair[0], ours + pair[1]
            rates[size] = blocks * block / ours
            relative[size] = floor / ours
            done += block + blocks * block
        get_all = latencies_us(200, lambda i: _timed(lambda: c.get_all(StringValue)))
        assert len(c.get_all(StringValue)) == 10
        rss = server.rss_bytes()
        c._cast_close()
        small, full = rates[checkpoints[0]], rates[checkpoints[-1]]
        return {
            "entries": done,
            "server_rss_mib": round(rss / 2**20, 1),
            "get_all_10_p50_ms": round(percentile(get_all, 50) / 1000, 3),
            "add_per_s_at_small": round(small),
            "add_per_s_at_full": round(full),
            "add_rate_ratio": round(relative[checkpoints[-1]] / relative[checkpoints[0]], 3),
            "relative_to_floor": {str(k): round(v, 3) for k, v in relative.items()},
            "rates": {str(k): round(v) for k, v in rates.items()},
        }
    finally:
        server.stop()


def _timed(fn: Any) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0
