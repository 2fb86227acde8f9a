"""M7: the C++ and Java clients, measured like the Python one (sequential Add; write -> event latency).

Each language has a small benchmark program built by the normal builds and kept
out of the libraries' APIs: ``build/cpp/bin/cast_bench`` (cpp_client/bench/cast_bench.cc,
``make cpp``) and ``cast.bench.Bench`` (java_client/src/test/java/cast/bench/, compiled
into target/test-classes by ``make java`` and run with the fat jar). Both take the
launch contract from the environment and a mode:

- ``add N WARM``: WARM warm-up adds (200 if not given), then N sequential adds of a
  100-byte BytesValue; prints ``{"per_s": ...}``. Used for Java's figure with the JIT
  still compiling.
- ``blocks WARM``: WARM warm-up adds, ``ready``, then for each line "B W" read on
  stdin, W untimed adds, B timed sequential adds and a line with the seconds they took.
- ``watch N``: a watch on address "lat" of its SA; prints ``ready``, then after N
  events ``{revision: CLOCK_MONOTONIC ns at callback time}``.
- ``write N GAP_MS [WARM [TURN SIDES]]``: adds "lat", WARM overwrites back to back, then N-1
  overwrites spaced by GAP_MS, stamping CLOCK_MONOTONIC ns just before each; prints
  ``{revision: ns}``. With TURN, every overwrite waits for its turn (:mod:`bench.turns`).

The Python client is measured again here and is the floor of every figure. Add:
each language's process is warmed up, then they take blocks of 100 sequential adds
in turn, the order rotating each cycle, against one ``cast serve``; between two
runs of a few seconds each a rate moves by 10% or more on this machine, so runs one
after the other (as this row was first measured) could not tell a 5% difference.
The latency is computed exactly as :func:`bench.cast_cases.m3_latency` does it for
Python (writer and watcher in separate processes, 2 ms spacing, the add and the
first tenth, at most 50, of the samples dropped as warm-up), the three languages
at once, in turns (:mod:`bench.turns`): each pair in an SA of its own, each writer
writing in every third second only, so that a spell of this machine slows all
three alike (one after the other, a spell could put C++ at 0.69 x Python's in one
run and 1.31 x in the next). Java's judged latency comes after JIT_WARM warm-up
writes in its turns; its latency without them is measured alone, before, and shown.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from bench import turns
from bench.cast_cases import VALUE, Server, m3_latency
from bench.floors import GAP_S
from bench.harness import ROOT, child_env, summary_us

CPP_BENCH = Path(os.environ.get("CAST_CPP_BIN_DIR") or ROOT / "build" / "cpp" / "bin") / "cast_bench"
JAVA_JAR = ROOT / "java_client" / "target" / "cast-client-all.jar"
JAVA_TEST_CLASSES = ROOT / "java_client" / "target" / "test-classes"
JAVA_BENCH_CLASS = "cast.bench.Bench"
TIMEOUT_S = 180
SA = "bench"  # the Add blocks' SA
LATENCY_SA = {"Python": "lat-python", "C++": "lat-cpp", "Java": "lat-java"}
"""Each language's write -> event latency pair writes and watches in an SA of its own: they run at once, in turns."""
# A client in a compiled language, on the write stream too, should not be held to Python's pace.
ADD_RATIO = 1.5


def cpp_command() -> list[str] | str:
    """The C++ benchmark program, or why it cannot run."""
    if not (CPP_BENCH.is_file() and os.access(CPP_BENCH, os.X_OK)):
        return f"C++ not built ({CPP_BENCH.relative_to(ROOT)} missing: run `make cpp`)"
    return [str(CPP_BENCH)]


def java_command() -> list[str] | str:
    """The Java benchmark program, or why it cannot run."""
    java = shutil.which("java")
    if java is None:
        return "Java not measured (no `java` on PATH: `make java` installs a JDK)"
    missing = [p for p in (JAVA_JAR, JAVA_TEST_CLASSES / "cast" / "bench" / "Bench.class") if not p.exists()]
    if missing:
        return f"Java not built ({', '.join(str(p.relative_to(ROOT)) for p in missing)} missing: run `make java`)"
    return [java, "-cp", os.pathsep.join([str(JAVA_JAR), str(JAVA_TEST_CLASSES)]), JAVA_BENCH_CLASS]


def _last_json(out: str, what: str) -> Any:
    lines = [line for line in out.strip().splitlines() if line.startswith("{")]
    if not lines:
        raise RuntimeError(f"{what} printed no result: {out[-500:]!r}")
    return json.loads(lines[-1])


def _tail(log: IO[str]) -> str:
    """The end of a process's log file, for an error message."""
    log.seek(0)
    return log.read()[-800:]


def _run(cmd: list[str], env: dict[str, str], what: str) -> Any:
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    if out.returncode != 0:
        raise RuntimeError(f"{what} exited {out.returncode}: {out.stderr[-800:]}")
    return _last_json(out.stdout, what)


def add_rate(cmd: list[str], server: Server, sa: str, n: int, tag: str, warm: int = 200) -> float:
    """Sequential Add calls/s of one component (`warm` adds first, 200 as for Python)."""
    out = _run([*cmd, "add", str(n), str(warm)], child_env(server.env(f"m7-add-{tag}", sa)), f"{cmd[-1]} add")
    return float(out["per_s"])


def latency(
    cmd: list[str], server: Server, sa: str, n: int, gap_s: float = GAP_S, warm: int = 0, tag: str = "",
    turn: int = turns.NONE, sides: int = 2,
) -> dict[str, Any]:
    """Write -> event latency: a writer process and a watcher process of the same language.

    With `warm`, the writer first overwrites that many times back to back (not measured);
    with a `turn` of `sides`, each of its overwrites waits for its turn (:mod:`bench.turns`).
    """
    # The watcher's log goes to a file: a pipe nobody reads could fill up and stop it.
    errors = tempfile.TemporaryFile("w+")
    watcher = subprocess.Popen(
        [*cmd, "watch", str(n + warm)],
        env=child_env(server.env(f"m7-watcher{tag}", sa)),
        stdout=subprocess.PIPE,
        stderr=errors,
        text=True,
    )

    try:
        assert watcher.stdout is not None
        first = watcher.stdout.readline().strip()
        if first != "ready":
            watcher.wait(10)
            raise RuntimeError(f"{cmd[-1]} watch did not start: {first!r} {_tail(errors)}")
        sent = {
            int(k): v
            for k, v in _run(
                [*cmd, "write", str(n), str(round(gap_s * 1000)), str(warm), str(turn), str(sides)],
                child_env(server.env(f"m7-writer{tag}", sa)),
                f"{cmd[-1]} write",
            ).items()
        }
        out, _ = watcher.communicate(timeout=TIMEOUT_S)
        if watcher.returncode != 0:
            raise RuntimeError(f"{cmd[-1]} watch exited {watcher.returncode}: {_tail(errors)}")
    finally:
        if watcher.poll() is None:
            watcher.kill()
            watcher.wait()
        errors.close()
    arrived = {int(k): v for k, v in _last_json(out, f"{cmd[-1]} watch").items()}
    # As m3_latency: samples in revision order, the add excluded (it is not in `sent`).
    samples = [(arrived[r] - t0) / 1e3 for r, t0 in sorted(sent.items()) if r in arrived]
    lost = len(sent) - len(samples)
    warm = min(50, len(samples) // 10)
    samples = samples[warm:]
    return {**summary_us(samples), "lost": lost, "samples_us": samples}


class Blocks:
    """A client process in ``blocks`` mode: warmed up, then timing blocks of sequential adds on demand."""

    def __init__(self, cmd: list[str], env: dict[str, str], warm: int, what: str) -> None:
        self.what = what
        self._errors = tempfile.TemporaryFile("w+")
        self._proc = subprocess.Popen(
            [*cmd, "blocks", str(warm)],
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._errors,
            text=True,
        )
        if self._line() != "ready":
            raise RuntimeError(f"{what} did not start: {_tail(self._errors)}")

    def _line(self) -> str:
        assert self._proc.stdout is not None
        return self._proc.stdout.readline().strip()

    def seconds(self, calls: int, warm: int = 0) -> float:
        """Seconds that ``calls`` sequential adds took in the client process, after ``warm`` untimed ones."""
        assert self._proc.stdin is not None
        self._proc.stdin.write(f"{calls} {warm}\n")
        self._proc.stdin.flush()
        line = self._line()
        try:
            return float(line)
        except ValueError:
            raise RuntimeError(f"{self.what} answered {line!r}: {_tail(self._errors)}") from None

    def close(self) -> None:
        """End the process (EOF on its stdin)."""
        if self._proc.stdin is not None:
            self._proc.stdin.close()
        try:
            self._proc.wait(30)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        self._errors.close()


class PythonBlocks:
    """The Python client's side of the interleaved Add blocks, in this process (as M1 measures it)."""

    def __init__(self, server: Server, sa: str, warm: int) -> None:
        self._c = server.component("m7-add-python", sa)
        self._counter = iter(range(10**9))
        self._untimed(warm)

    def _untimed(self, calls: int) -> None:
        for _ in range(calls):
            self._c.add(f"m7-python-{next(self._counter)}", VALUE)

    def seconds(self, calls: int, warm: int = 0) -> float:
        """Seconds that ``calls`` sequential adds took, after ``warm`` untimed ones."""
        self._untimed(warm)
        ids = [f"m7-python-{next(self._counter)}" for _ in range(calls)]
        t0 = time.perf_counter()
        for entry_id in ids:
            self._c.add(entry_id, VALUE)
        return time.perf_counter() - t0

    def close(self) -> None:
        """Unbind the component."""
        self._c._cast_close()


def interleaved_add_rates(
    clients: dict[str, Blocks | PythonBlocks], calls: int, block: int = 100, warm: int = 20
) -> dict[str, float]:
    """Sequential Add calls/s of each client, measured in blocks taken in turn.

    The order of the turn rotates every cycle, so each client follows each other
    one equally often; a change in the machine's speed, which between two runs of
    a few seconds each moves a rate by 10% or more here, hits every client alike.
    Each block starts with ``warm`` untimed calls: a client whose process sat idle
    while the others took their turns is slow for its first calls (grpcio's
    Python client much more than gRPC C++: see docs/performance.md), and the
    figure is the sequential rate, not the cost of waking up.
    """
    labels = list(clients)
    seconds = dict.fromkeys(labels, 0.0)
    cycles = max(1, calls // block)
    for k in range(cycles):
        shift = k % len(labels)
        for label in labels[shift:] + labels[:shift]:
            seconds[label] += clients[label].seconds(block, warm)
    return {label: cycles * block / s for label, s in seconds.items()}


def run(
    workdir: Path,
    n: int,
    python_add_per_s: float,
    python_latency_p50: float,
    rounds: int = 1,
    jit_warm: int = 20_000,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """The M7 row: figures for each client library that is built, the Python client's as the floor.

    The floors are the Python client measured again here, the same way as M1 and M3
    (`python_add_per_s` and `python_latency_p50`, this run's M1 and M3, are kept in
    the row for reference). Add: one process per language, each warmed up, then
    blocks of 100 sequential adds taken in turn (:func:`interleaved_add_rates`),
    ``n * rounds`` adds each. Latency: measured one language after the other. All
    on one `cast serve`.

    Whether the target is met is judged at steady state, as JVM benchmarks are
    (JMH warms up before it measures): Python and C++ run no JIT and are steady
    after 200 warm-up calls; Java is judged after `jit_warm` warm-up calls, and its
    figures after 200 (the JIT still compiling, measured in a run of its own) are
    shown too.
    """
    notes: list[str] = []
    met = True
    commands: dict[str, list[str]] = {}
    for label, command in (("C++", cpp_command()), ("Java", java_command())):
        if isinstance(command, str):
            notes.append(command)
            met = False
        else:
            commands[label] = command
    labels = ["Python", *commands]
    failed: dict[str, str] = {}
    rates: dict[str, float] = {}
    lat: dict[str, dict[str, Any]] = {}
    jit: dict[str, Any] = {}
    server = Server(workdir, [SA, *LATENCY_SA.values()])

    def attempt(label: str, what: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        if label in failed:
            return None
        log(f"M7 {label} {what}")
        try:
            return fn(*args, **kwargs)
        except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
            failed[label] = f"{what}: {exc}"
            return None

    def blocks(label: str) -> Blocks | PythonBlocks:
        if label == "Python":
            return PythonBlocks(server, SA, 200)
        warm = jit_warm if label == "Java" and jit_warm else 200
        return Blocks(commands[label], child_env(server.env(f"m7-add-{label.lower()}", SA)), warm, f"{label} blocks")

    def event_latency(label: str, warm: int = 0, turn: int = turns.NONE, sides: int = 2) -> dict[str, Any]:
        sa = LATENCY_SA[label]
        if label == "Python":
            return m3_latency(server, n, sa=sa, turn=turn, sides=sides)
        return latency(commands[label], server, sa, n, warm=warm, tag=f"-{label.lower()}-w{warm}", turn=turn,
                       sides=sides)

    def latencies_in_turns() -> None:
        """Every language's latency at once, each writer in its turn; Java's after its JIT warm-up (judged)."""
        warm = {"Java": jit_warm} if jit_warm else {}
        live = [label for label in labels if label not in failed]
        got: dict[str, Any] = {}

        def one(label: str, turn: int) -> None:
            got[label] = attempt(label, "write -> event latency, in turns", event_latency, label,
                                 warm=warm.get(label, 0), turn=turn, sides=len(live))

        log(f"M7 write -> event latency: {', '.join(live)} at once, in turns of a second")
        threads = [threading.Thread(target=one, args=(label, turn), name=f"m7-{label}")
                   for turn, label in enumerate(live, 1)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        for label, result in got.items():
            if result is not None:
                if label == "Java" and jit_warm:
                    jit["latency"] = result
                else:
                    lat[label] = result

    clients: dict[str, Blocks | PythonBlocks] = {}
    try:
        if "Java" in commands:
            jit["cold_add_per_s"] = attempt(
                "Java", "sequential Add after 200 warm-up calls", add_rate, commands["Java"], server, SA, n, "java-cold"
            )
        for label in labels:
            got = attempt(label, "warm-up for the interleaved Add blocks", blocks, label)
            if got is not None:
                clients[label] = got
        log(f"M7 sequential Add: {', '.join(clients)} in turn, blocks of 100, {n * rounds:,} calls each")
        try:
            rates = interleaved_add_rates(clients, n * rounds)
        except (RuntimeError, OSError) as exc:
            for label in clients:
                failed.setdefault(label, f"interleaved Add: {exc}")
        if "Java" in commands and jit_warm:  # shown beside the judged one: the JIT still compiling, alone
            cold = attempt("Java", "write -> event latency without warm-up writes", event_latency, "Java")
            if cold is not None:
                lat["Java"] = cold
        latencies_in_turns()
    finally:
        for client in clients.values():
            client.close()
        server.stop()

    figures: list[dict[str, Any]] = []
    samples: dict[str, list[float]] = {}
    if "Python" in failed:
        notes.append(f"the Python reference failed ({failed['Python']}): this run's M1 and M3 are the floors")
    py_add = round(rates["Python"]) if "Python" in rates else python_add_per_s
    py_p50 = lat["Python"]["p50_us"] if "Python" in lat else python_latency_p50
    lat_target = 1.2 * py_p50
    for label in commands:
        if label in failed:
            notes.append(f"{label} failed: {failed[label]}")
            met = False
            continue
        add = round(rates[label])
        m = lat[label]
        samples[f"{label} -> {label}"] = m["samples_us"]
        # Java's Add from the interleaved blocks is after the JIT warm-up; the cold one had a run of its own.
        at_steady_state = label == "Java" and jit.get("cold_add_per_s") and jit.get("latency")
        shown_add = round(jit["cold_add_per_s"]) if at_steady_state else add
        figures += [
            {"name": f"{label} Add (calls/s)", "value": shown_add, "floor": py_add},
            {"name": f"{label} -> {label} latency p50 (µs)", "value": m["p50_us"], "floor": py_p50},
            {"name": f"{label} -> {label} latency p99 (µs)", "value": m["p99_us"]},
            {"name": f"{label} lost events", "value": m["lost"]},
        ]
        judged_p50 = m["p50_us"]
        if at_steady_state:
            jit_lat = jit["latency"]
            judged_p50 = jit_lat["p50_us"]
            samples[f"{label} -> {label}, after {jit_warm:,} warm-up writes"] = jit_lat["samples_us"]
            figures += [
                {
                    "name": f"{label} Add after {jit_warm:,} warm-up calls (calls/s), judged",
                    "value": add,
                    "floor": py_add,
                },
                {
                    "name": f"{label} latency p50 after {jit_warm:,} warm-up writes (µs), judged",
                    "value": jit_lat["p50_us"],
                    "floor": py_p50,
                },
                {"name": f"{label} latency p99 after {jit_warm:,} warm-up writes (µs)", "value": jit_lat["p99_us"]},
            ]
            if shown_add < py_add or m["p50_us"] > lat_target:
                notes.append(
                    f"{label}: with 200 warm-up calls the JVM is still compiling the call path (JIT): {shown_add} "
                    f"Add/s ({shown_add / py_add:.2f} x Python's), latency p50 {m['p50_us']} µs "
                    f"({m['p50_us'] / py_p50:.2f} x Python's); judged at steady state, after {jit_warm:,} warm-up "
                    "calls; see docs/performance.md, M7"
                )
        ok_add = add >= ADD_RATIO * py_add
        ok_lat = judged_p50 <= lat_target
        met = met and ok_add and ok_lat and m["lost"] == 0
        misses = []
        if not ok_add:
            misses.append(f"Add {add} calls/s < {ADD_RATIO} x Python's {py_add}")
        if not ok_lat:
            misses.append(f"latency p50 {judged_p50} µs > 1.2 x Python's ({lat_target:.0f} µs)")
        if m["lost"]:
            misses.append(f"{m['lost']} events lost")
        if misses:
            notes.append(f"{label}: " + "; ".join(misses))
    row: dict[str, Any] = {
        "id": "M7",
        "what": "C++ and Java clients: sequential Add; write -> event latency to a watcher in the same language "
        "(floor: the Python client, measured here too: Add in blocks taken in turn with theirs)",
        "target": f"Add calls/s >= {ADD_RATIO} x the Python client's; latency p50 <= 1.2 x the Python client's",
        "figures": figures
        or [
            {"name": "Python Add (calls/s)", "value": py_add},
            {"name": "Python -> Python latency p50 (µs)", "value": py_p50},
        ],
        "met": met,
        "python_m1_m3": {"add_per_s": python_add_per_s, "p50_us": python_latency_p50},
        # Taken out by bench/run.py for the latency plot (not written to the JSON).
        "samples_us": samples,
    }
    if notes:
        row["note"] = "; ".join(notes)
    return row
