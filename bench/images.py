"""M8: image-sized entries. A C++ writer overwrites an entry of 1 MiB or 6 MiB; four watchers read every byte.

Watchers, each a process of its own: Python, C++, Java, Python
(bench/image_watcher.py, ``cast_bench image-watch``, ``cast.bench.Bench
image-watch``), all watching the entry with its value and reading every byte
of every image in place through the library's ``ValueView`` (a checksum,
bench.checksum, checked against what the writer wrote; on the server's host
the value is lent by shared memory, nothing copied). The writer is
``cast_bench image-write`` (sequential overwrites, staged in shared memory).

Phases on one ``cast serve`` (new watcher processes each, the server's memory
sampled throughout, :class:`ServerMemory`): ``queue`` delivery of 1 MiB at
30 Hz, of 6 MiB (a 1080p RGB frame) at 30 Hz, of 1 MiB back to back, and
``latest`` delivery of 1 MiB back to back. The judged 1 MiB 30 Hz phase and
Zenoh's run at once, each writing in its own seconds (:func:`in_turns`,
bench/turns.py). Then a remote phase: a server
listening on a veth pair to another network namespace (bench.other_host) and
a Python watcher in that namespace, which gets every value as bytes.

In the same run: Zenoh (bench/zenoh_peer.py) and iceoryx2
(bench/iceoryx2_peer.py, the zero-copy limit), each a Python publisher and
four Python subscribers that read every byte of every message, carry the same
sizes at the same paces; at 1 MiB and 30 Hz so does a bare Python relay
between one writer and four readers (bench/relay_floor.py: CAST's two hops and
one copy, without its rules), for what the path itself costs; the bare gRPC
unary echo of 1 MiB (bench/floors.py) is measured once, for context.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import tempfile
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any, NamedTuple

from bench import iceoryx2_peer, relay_floor, turns, zenoh_peer
from bench.cast_cases import Server
from bench.checksum import expected_cast, expected_frames
from bench.delivery_stats import ordinal, parse_watcher, settling, totals, watcher_figures
from bench.floors import EchoFloor
from bench.harness import PYTHON, ROOT, child_env
from bench.other_clients import cpp_command, java_command
from bench.other_host import OtherHost
from bench.peer_fanout import WARM_BURST, WARM_PAUSE_S
from bench.server_memory import ServerMemory, idle_memory

__all__ = [
    "BIG", "HISTORY_BYTES", "HZ", "PHASES", "SIZE", "WATCHERS", "Recorded", "ServerMemory", "in_turns", "record_phase",
    "run",
]

SIZE = 1 << 20  # a VGA RGB image is 0.9 MiB
BIG = 6 << 20  # a 1080p RGB image is 5.9 MiB
HZ = 30
SA = "images"
# M8's server keeps at most this many bytes of values in its history (limits.history_bytes, which counts the
# values it keeps in shared memory too): small enough that a run fills it, so the memory bound is exercised.
HISTORY_BYTES = 64 << 20
WATCHERS = ("Python 1", "C++", "Java", "Python 2")
REMOTE = "Python, other host"
# (key, delivery, value size, paced at HZ): the phases on the server's host.
PHASES: tuple[tuple[str, str, int, bool], ...] = (
    ("queue_hz", "queue", SIZE, True),
    ("queue_hz_6m", "queue", BIG, True),
    ("queue_b2b", "queue", SIZE, False),
    ("latest_b2b", "latest", SIZE, False),
)
# Before each phase's measured frames the writer sends WARM_PER_FRAME x as many (of 1 MiB) back to back, each
# of WARM_SIZE bytes: a warm-up on the readers' real path (a value lent by shared memory, every byte read), so
# that they are judged at steady state as M7 judges Java (docs/decisions.md). As many as that so that the Java
# watcher's per-frame methods pass the JVM's thresholds for its optimising compiler (C2: 5,000 calls, more
# while its queue is long): with 4 x as many (1,200) they all still ran as C1's profiling code when measured
# (-XX:+LogCompilation; docs/performance-m8.md, "The warm-up reaches C2"). Values of the smallest size that goes
# by shared memory, so that the history (HISTORY_BYTES) holds 1,024 of them: a cold reader would have to fall
# that far behind to lose its watch (64 values of 1 MiB did once), which the bursts with pauses between them
# (bench.peer_fanout.WARM_BURST, for the peers alike) keep it from doing. The 1 MiB 30 Hz phase begins with COLD_S of
# paced frames before that, every reader cold (its "first seconds": shown, not judged).
WARM_PER_FRAME = 34
WARM_SIZE = 64 << 10  # shared_memory.threshold_bytes' default
COLD_S = 2
# The judged comparison (1 MiB at 30 Hz, each watcher's p50 against Zenoh's) runs the two at once, in turns
# (bench.turns): CAST's writer in the even seconds, Zenoh's publisher in the odd ones, JUDGED_FRAMES x a phase's
# frames each, so that both meet the machine as it is in the same minute; each side's halves are shown beside.
JUDGED_FRAMES = 2
TIMEOUT_S = 300  # the writer's whole run
AFTER_WRITER_S = 60  # how long the watchers may take to finish once the writer is done


def _watcher_command(label: str, delivery: str) -> list[str] | str:
    if label.startswith("Python"):
        return [PYTHON, "-m", "bench.image_watcher", delivery]
    command = cpp_command() if label == "C++" else java_command()
    return command if isinstance(command, str) else [*command, "image-watch", delivery]


class _Watchers:
    """The watcher processes of one phase: (label, command) each."""

    def __init__(self, server: Server, commands: Sequence[tuple[str, list[str] | str]], tag: str) -> None:
        self.labels: list[str] = []
        self.procs: list[subprocess.Popen[str]] = []
        self.logs: list[IO[str]] = []
        self.missing: dict[str, str] = {}
        for i, (label, command) in enumerate(commands):
            if isinstance(command, str):
                self.missing[label] = command
                continue
            log: IO[str] = tempfile.TemporaryFile("w+")
            env = child_env(server.env(f"m8-{tag}-w{i}", SA))
            self.procs.append(subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=log, text=True,
                                               cwd=ROOT))
            self.labels.append(label)
            self.logs.append(log)
        for label, proc, log in zip(self.labels, self.procs, self.logs, strict=True):
            assert proc.stdout is not None
            line = proc.stdout.readline().strip()
            if line != "ready":
                raise RuntimeError(f"{label} watcher did not start: {line!r} {_tail(log)}")

    def results(self) -> dict[str, dict[str, Any]]:
        out = {}
        for label, proc, log in zip(self.labels, self.procs, self.logs, strict=True):
            try:
                text, _ = proc.communicate(timeout=AFTER_WRITER_S)
            except subprocess.TimeoutExpired:
                raise RuntimeError(f"{label} watcher had not seen the end {AFTER_WRITER_S} s after the writer: "
                                   f"{_tail(log)}") from None
            lines = [line for line in text.splitlines() if line.startswith("{")]
            if proc.returncode != 0 or not lines:
                raise RuntimeError(f"{label} watcher exited {proc.returncode}: {_tail(log)}")
            out[label] = parse_watcher(json.loads(lines[-1]))
            ended = _watch_ended(log)
            if ended:
                out[label]["watch_ended"] = ended
        return out

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in self.logs:
            log.close()


def _watch_ended(log: IO[str]) -> str:
    """The line where a watcher's library said its watch ended early (fell behind the history, say), or ""."""
    log.seek(0)
    for line in log.read().splitlines():
        if "HistoryExpiredError" in line or "change delivery stopped" in line or "watch failed" in line:
            return line.strip()[-300:]
    return ""


def _tail(log: IO[str]) -> str:
    log.seek(0)
    return log.read()[-800:]


def _write(server: Server, command: list[str], tag: str) -> dict[int, int]:
    env = child_env(server.env(f"m8-{tag}-writer", SA))
    out = subprocess.run(command, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    lines = [line for line in out.stdout.splitlines() if line.startswith("{")]
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"the C++ writer exited {out.returncode}: {out.stderr[-800:]}")
    return {int(k): int(v) for k, v in json.loads(lines[-1]).items()}


def _measured(got: dict[str, Any], keys: dict[int, int], size: int) -> dict[str, Any]:
    """A watcher's result cut to the writes ``keys``: their stamps, and their bytes (``size`` each)."""
    stamps = {k: t for k, t in got["stamps"].items() if k in keys}
    return {**got, "stamps": stamps, "bytes": size * len(stamps)}


def figures(sent: dict[int, int], got: dict[str, dict[str, Any]], extra: int,
            expected: Callable[[dict[str, Any]], int], size: int, warm: int = 0, cold: int = 0) -> dict[str, Any]:
    """Each watcher's figures, whether it read the bytes written, and the total.

    ``sent`` is every write (key -> stamp), in key order ``cold`` writes in the
    readers' first seconds, then ``warm`` warm-up writes, then the measured
    ones (:func:`bench.peer_fanout.drive`, ``cast_bench image-write``). The
    latencies and MB/s are of the measured writes, their first tenth (at most
    30) dropped as warm-up too; ``cold_p50_us``/``cold_p99_us`` (with ``cold``)
    of the first ``cold`` ones. Lost, received, the bytes and the checksum are of
    every write: ``checksum_ok`` is whether it is ``expected(the result)``.
    """
    order = sorted(sent)
    measured = {k: sent[k] for k in order[cold + warm:]}
    early = {k: sent[k] for k in order[:cold]}
    late = dict(sorted(measured.items())[settling(len(measured)):])
    per = {}
    mine = {label: _measured(g, measured, size) for label, g in got.items()}
    for label, g in got.items():
        whole = watcher_figures(sent, g, extra)
        steady = watcher_figures(late, mine[label])
        per[label] = {**whole, "p50_us": steady["p50_us"], "p99_us": steady["p99_us"], "mean_us": steady["mean_us"],
                      "samples_us": steady["samples_us"],
                      "mb_per_s": watcher_figures(measured, mine[label])["mb_per_s"], "bytes": g["bytes"],
                      "checksum_ok": g.get("checksum") == expected(g)}
        if early:
            first = watcher_figures(early, _measured(g, early, size))
            per[label] |= {"cold_p50_us": first["p50_us"], "cold_p99_us": first["p99_us"]}
        if "shared" in g:
            per[label]["shared"] = g["shared"]
        if "watch_ended" in g:
            per[label]["watch_ended"] = g["watch_ended"]
    return {"watchers": per, "total": totals(measured, list(mine.values())), "frames": len(measured),
            "warm": warm, "cold": cold}


def _warm_sizes(sent: dict[int, int], warm: int, cold: int) -> dict[int, int]:
    """The warm-up writes' keys (after the ``cold`` first ones), each with its value's size, WARM_SIZE."""
    return {k: WARM_SIZE for k in sorted(sent)[cold:cold + warm]}


class Recorded(NamedTuple):
    """What one phase on CAST gave, before any figure: every write's stamp and each watcher's own result."""

    sent: dict[int, int]  # revision -> the writer's CLOCK_MONOTONIC stamp (ns) just before the overwrite
    got: dict[str, dict[str, Any]]  # label -> the watcher's result (bench.delivery_stats.parse_watcher)
    peaks: dict[str, int]  # the server's memory (ServerMemory.stop)
    missing: dict[str, str]  # label -> why that watcher did not run (its program is not built, ...)


def record_phase(server: Server, writer: list[str], commands: Sequence[tuple[str, list[str] | str]], size: int,
                 frames: int, gap_s: float, tag: str, warm: int = 0, cold: int = 0) -> Recorded:
    """One phase on CAST: new watchers, the C++ writer, the server's memory meanwhile; what it gave, raw.

    The writer sends ``cold`` paced values, ``warm`` of WARM_SIZE bytes back
    to back in bursts (as :func:`bench.peer_fanout.drive`), then ``frames``
    values of ``size`` bytes every ``gap_s`` seconds.
    """
    watchers = _Watchers(server, commands, tag)
    try:
        memory = ServerMemory(server.proc.process.pid)
        try:
            sent = _write(server, [*writer, "image-write", str(size), str(frames), str(round(gap_s * 1e6)),
                                   str(warm), str(WARM_SIZE), str(cold), str(WARM_BURST),
                                   str(round(WARM_PAUSE_S * 1e6))], tag)
            got = watchers.results()
        finally:
            peaks = memory.stop()
    finally:
        watchers.close()
    return Recorded(sent, got, peaks, watchers.missing)


def cast_phase(server: Server, writer: list[str], commands: Sequence[tuple[str, list[str] | str]], size: int,
               frames: int, gap_s: float, tag: str, warm: int = 0, cold: int = 0) -> dict[str, Any]:
    """One phase on CAST (:func:`record_phase`), and its figures: the ``frames`` measured (:func:`figures`)."""
    run_ = record_phase(server, writer, commands, size, frames, gap_s, tag, warm, cold)
    sent = run_.sent
    sizes = _warm_sizes(sent, warm, cold)
    out = figures(sent, run_.got, 2, lambda g: expected_cast(sent, g["stamps"], size, sizes), size, warm, cold)
    return {**out, "size": size, "server_memory": run_.peaks, "missing": run_.missing}


def _remote_phase(workdir: Path, writer: list[str], frames: int) -> dict[str, Any]:
    """1 MiB at HZ to a Python watcher in another network namespace (bytes), the server listening on the pair."""
    with OtherHost() as host:
        server = Server(workdir, [SA], limits={"history_bytes": HISTORY_BYTES}, listen=f"{host.address}:0")
        try:
            command = [*host.prefix, PYTHON, "-m", "bench.image_watcher", "queue"]
            return cast_phase(server, writer, [(REMOTE, command)], SIZE, frames, 1 / HZ, "remote")
        finally:
            server.stop()


def _peer(fn: Callable[..., dict[str, Any]], frames: int, gap_s: float, size: int, warm: int = 0,
          cold: int = 0, **more: Any) -> dict[str, Any]:
    run_ = fn(frames, gap_s, size, warm=warm, warm_size=WARM_SIZE, cold=cold, **more)
    labels = [f"subscriber {i + 1}" for i in range(len(run_["watchers"]))]
    sizes = _warm_sizes(run_["sent"], warm, cold)
    return {**figures(run_["sent"], dict(zip(labels, run_["watchers"], strict=True)), 0,
                      lambda g: expected_frames(g["stamps"], size, sizes), size, warm, cold), "size": size}


def _guard(out: dict[str, Any], key: str, fn: Callable[..., dict[str, Any]], *args: Any) -> None:
    """``out[key] = fn(*args)``, or the error that stopped it (the row reports it)."""
    try:
        out[key] = fn(*args)
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        out[key] = {"error": str(exc)}


def _judged(out: dict[str, Any], server: Server, writer: list[str], frames: int, cold: int,
            log: Callable[[str], None]) -> None:
    """CAST's 1 MiB 30 Hz phase and Zenoh's, at once and in turns (:func:`in_turns`)."""
    log(f"M8 CAST queue_hz and Zenoh: 1 MiB, {HZ} Hz, in turns (CAST the even seconds, Zenoh the odd ones)")
    try:
        cast, peer = in_turns(server, writer, JUDGED_FRAMES * frames, cold, WARM_PER_FRAME * frames)
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        cast = peer = {"error": f"the phase in turns: {exc}"}
    out["cast_queue_hz"], out["zenoh_hz"] = cast, peer
    for side in (cast, peer):
        for number, half in enumerate(side.get("halves", ()), 1):
            log(f"  {'CAST' if side is cast else 'Zenoh'}, the {ordinal(number)} half, p50 (µs): "
                + ", ".join(f"{label} {p50:.0f}" for label, p50 in half.items()))


def in_turns(server: Server, writer: list[str], frames: int, cold: int, warm: int
             ) -> tuple[dict[str, Any], dict[str, Any]]:
    """CAST's 1 MiB 30 Hz phase and Zenoh's at once, each writing in its turn (bench.turns): both results.

    CAST's watchers start, its writer (``cast_bench image-write`` with turn
    CAST) sends ``cold`` paced frames and ``warm`` back to back and says
    "warm"; then Zenoh's subscribers start and its publisher does the same
    (turn PEER); then both write their ``frames``, each in its own seconds.
    Each result is :func:`figures`' for that side, with ``halves``: its
    watchers' p50s over the first and over the second half of its measured
    frames, to show how much the two systems moved together. The server's
    memory is sampled between the turns (:class:`ServerMemory`). Raises RuntimeError when CAST's
    side fails (Zenoh's side's own failure is its result's ``error``).
    """
    commands = [(label, _watcher_command(label, "queue")) for label in WATCHERS]
    command = [*writer, "image-write", str(SIZE), str(frames), str(round(1e6 / HZ)), str(warm), str(WARM_SIZE),
               str(cold), str(WARM_BURST), str(round(WARM_PAUSE_S * 1e6)), str(turns.CAST)]
    go, peer_warm = threading.Event(), threading.Event()
    peer: dict[str, Any] = {"error": "not measured: CAST's side failed before its turns began"}

    def warmed() -> None:  # Zenoh's publisher, warmed up: waits for CAST's writer to be told too
        peer_warm.set()
        go.wait(TIMEOUT_S)

    def zenoh() -> None:
        try:
            peer.update(_peer(zenoh_peer.large, frames, 1 / HZ, SIZE, warm, cold, turn=turns.PEER, go=warmed))
            peer.pop("error")
        except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
            peer["error"] = f"Zenoh's side: {exc}"
        finally:
            peer_warm.set()

    thread = threading.Thread(target=zenoh, name="m8-zenoh", daemon=True)
    watchers = _Watchers(server, commands, "queue_hz")
    try:
        memory = ServerMemory(server.proc.process.pid, between_turns=True)
        try:
            sent = _write_in_turns(server, command, thread, peer_warm, go)
            got = watchers.results()
        finally:
            peaks = memory.stop()
    finally:
        go.set()  # Zenoh's side never waits for a writer that failed
        watchers.close()
        if thread.ident is not None:
            thread.join(TIMEOUT_S)
    sizes = _warm_sizes(sent, warm, cold)
    cast = figures(sent, got, 2, lambda g: expected_cast(sent, g["stamps"], SIZE, sizes), SIZE, warm, cold)
    cast |= {"size": SIZE, "server_memory": peaks, "missing": watchers.missing}
    return {**cast, "halves": _halves(cast)}, ({**peer, "halves": _halves(peer)} if "watchers" in peer else peer)


def _write_in_turns(server: Server, command: list[str], peer: threading.Thread, peer_warm: threading.Event,
                    go: threading.Event) -> dict[int, int]:
    """Run CAST's writer with its turn: once it and ``peer`` are warm, tell both to go; the writer's stamps."""
    with tempfile.TemporaryFile("w+") as errors:
        proc = subprocess.Popen(command, env=child_env(server.env("m8-queue_hz-writer", SA)), stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=errors, text=True, cwd=ROOT)
        watchdog = threading.Timer(TIMEOUT_S, proc.kill)  # a writer that hangs ends the phase, not the run
        watchdog.start()
        try:
            assert proc.stdin is not None and proc.stdout is not None
            line = proc.stdout.readline().strip()
            if line != "warm":
                raise RuntimeError(f"the C++ writer did not warm up ({line!r}): {_tail(errors)}")
            peer.start()
            peer_warm.wait(TIMEOUT_S)
            go.set()
            proc.stdin.write("go\n")
            proc.stdin.flush()
            text, _ = proc.communicate(timeout=TIMEOUT_S)
            lines = [line for line in text.splitlines() if line.startswith("{")]
            if proc.returncode != 0 or not lines:
                raise RuntimeError(f"the C++ writer exited {proc.returncode}: {_tail(errors)}")
        finally:
            watchdog.cancel()
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return {int(k): int(v) for k, v in json.loads(lines[-1]).items()}


def _halves(result: dict[str, Any]) -> list[dict[str, float]]:
    """Each watcher's p50 (µs) over the first and over the second half of its measured frames."""
    halves: list[dict[str, float]] = [{}, {}]
    for label, w in result.get("watchers", {}).items():
        samples = w.get("samples_us", [])
        middle = len(samples) // 2
        for half, part in zip(halves, (samples[:middle], samples[middle:]), strict=True):
            if part:
                half[label] = round(float(statistics.median(part)), 1)
    return halves


def run(workdir: Path, frames: int, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every phase of M8 and its peers and floor; raw results for bench/rows_scale.py.

    ``frames`` writes of 1 MiB per phase, half as many (at least 15) of 6 MiB,
    a fifth (at least 15) to the other host.
    """
    writer = cpp_command()
    if isinstance(writer, str):
        return {"error": writer}
    big_frames, remote_frames = max(15, frames // 2), max(15, frames // 5)
    count = {SIZE: frames, BIG: big_frames}
    cold = min(COLD_S * HZ, max(3, frames // 5))
    out: dict[str, Any] = {"size": SIZE, "big": BIG, "hz": HZ, "history_bytes": HISTORY_BYTES, "floor": [],
                           "cold_s": round(cold / HZ, 1)}
    server = Server(workdir / "cast", [SA], limits={"history_bytes": HISTORY_BYTES})
    try:
        out["server_memory_idle"] = idle_memory(server.proc.process.pid)
        _judged(out, server, writer, frames, cold, log)
        for key, delivery, size, paced in PHASES:
            if key == "queue_hz":
                continue  # measured in turns with Zenoh's, above
            log(f"M8 CAST {key}: {size >> 20} MiB, {delivery}, {f'{HZ} Hz' if paced else 'back to back'}")
            commands = [(label, _watcher_command(label, delivery)) for label in WATCHERS]
            _guard(out, f"cast_{key}", cast_phase, server, writer, commands, size, count[size],
                   1 / HZ if paced else 0.0, key, WARM_PER_FRAME * frames)
        out["server_memory_end"] = idle_memory(server.proc.process.pid)
    finally:
        server.stop()
    log(f"M8 CAST remote: 1 MiB at {HZ} Hz to a watcher in another network namespace")
    _guard(out, "cast_remote", _remote_phase, workdir / "remote", writer, remote_frames)
    log("M8 floor: bare gRPC echo of 1 MiB")
    echo = EchoFloor()
    try:
        out["floor"].append(echo.big_echo(max(20, frames // 2), SIZE))
    finally:
        echo.close()
    for name, fn in (("zenoh", zenoh_peer.large), ("iceoryx2", iceoryx2_peer.large), ("relay", relay_floor.large)):
        for key, size, paced in (("hz", SIZE, True), ("hz_6m", BIG, True), ("b2b", SIZE, False)):
            if (name == "iceoryx2" and size == BIG) or (name == "relay" and key != "hz") or f"{name}_{key}" in out:
                continue  # the limit is shown at 1 MiB; the relay beside the latency judged; Zenoh's judged done
            log(f"M8 {name}: {size >> 20} MiB, {f'{HZ} Hz' if paced else 'back to back'}")
            _guard(out, f"{name}_{key}", _peer, fn, count[size], 1 / HZ if paced else 0.0, size,
                   WARM_PER_FRAME * frames, cold if key == "hz" else 0)
    for result in out.values():  # the latencies themselves were for pooling; the figures stay
        if isinstance(result, dict):
            for w in result.get("watchers", {}).values():
                w.pop("samples_us", None)
    return out
