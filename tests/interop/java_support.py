"""Running Java components from pytest: the built library, a line protocol to drive them, RichEntry.

The Java side is ``cast.itest.Driven`` (java_client/src/test/java/cast/itest/):
each stdin line is a JSON command, each answer a JSON line on stdout; hooks
print ``{"event": ...}`` lines. ``make test`` builds the jar and the test
classes first (``make java``); a missing build fails the tests, it never skips
them.
"""

from __future__ import annotations

import json
import math
import os
import queue
import shutil
import threading
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.message import Message

from cast.testing import RunningSystem, run_system
from tests.interop.child import ChildProcess

ROOT = Path(__file__).resolve().parents[2]
JAVA_DIR = ROOT / "java_client"
JAR = JAVA_DIR / "target" / "cast-client-all.jar"
TEST_CLASSES = JAVA_DIR / "target" / "test-classes"
RUNNER = "cast.client.Runner"


def java_classpath(*extra: Path) -> str:
    """The class path of a Java component process; fails the test when the build is missing."""
    if shutil.which("java") is None:
        pytest.fail("java is not installed: the Java interop tests need a JDK 17 (java on PATH)")
    missing = [p for p in (JAR, TEST_CLASSES / "cast" / "itest" / "Driven.class") if not p.exists()]
    if missing:
        pytest.fail(f"the Java client is not built ({', '.join(map(str, missing))} missing): run `make java` first")
    return os.pathsep.join(str(p) for p in (JAR, TEST_CLASSES, *extra))


class JavaComponent(ChildProcess):
    """A ``cast.itest.Driven`` process (or any component class) started with the launch contract."""

    def __init__(self, env: dict[str, str], cls: str = "cast.itest.Driven", classpath: str | None = None) -> None:
        self.cls = cls
        self.replies: dict[int, dict[str, Any]] = {}
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self._seq = 0
        self._cond = threading.Condition()
        super().__init__(cls, ["java", "-cp", classpath or java_classpath(), RUNNER, cls], env, stdin=True)

    def on_line(self, line: str) -> None:
        """A reply goes to its caller, an event to :meth:`wait_event`; other lines are only kept."""
        try:
            msg = json.loads(line)
        except json.JSONDecodeError:
            return
        if "reply" in msg:
            with self._cond:
                self.replies[msg["reply"]] = msg
                self._cond.notify_all()
        elif "event" in msg:
            self.events.put(msg)

    def on_end(self) -> None:
        """Wake the callers waiting for a reply: none will come."""
        with self._cond:
            self._cond.notify_all()

    def wait_event(self, kind: str, timeout: float = 30.0) -> dict[str, Any]:
        """The next event of ``kind`` (events of other kinds before it are dropped)."""
        try:
            while True:
                ev = self.events.get(timeout=timeout)
                if ev["event"] == kind:
                    return ev
        except queue.Empty:
            raise AssertionError(f"no '{kind}' event from {self.cls} within {timeout} s\n{self.output()}") from None

    def no_event(self, kind: str, within: float) -> None:
        """Assert that no event of ``kind`` arrives within ``within`` seconds."""
        try:
            while True:
                ev = self.events.get(timeout=within)
                if ev["event"] == kind:
                    raise AssertionError(f"unexpected '{kind}' event: {ev}")
        except queue.Empty:
            return

    def ready(self, timeout: float = 60.0) -> dict[str, Any]:
        """Wait until the component is connected and started."""
        return self.wait_event("ready", timeout)

    def send(self, op: str, **kw: Any) -> int:
        """Send a command without waiting for its answer; returns its sequence number."""
        assert self.proc.stdin is not None
        self._seq += 1
        self.proc.stdin.write(json.dumps({"seq": self._seq, "op": op, **kw}) + "\n")
        self.proc.stdin.flush()
        return self._seq

    def reply(self, seq: int, timeout: float = 30.0) -> dict[str, Any]:
        """The answer to command ``seq``."""
        with self._cond:
            if not self._cond.wait_for(lambda: seq in self.replies or self.proc.poll() is not None, timeout):
                raise AssertionError(f"no answer to command {seq} within {timeout} s\n{self.output()}")
            if seq not in self.replies:
                raise AssertionError(f"{self.cls} exited ({self.proc.returncode}) before answering\n{self.output()}")
            return self.replies.pop(seq)

    def call(self, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]:
        """Send a command and return its answer (ok or not)."""
        return self.reply(self.send(op, **kw), timeout)

    def ok(self, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]:
        """Send a command that must succeed."""
        r = self.call(op, timeout, **kw)
        assert r["ok"], f"{op} {kw} failed: {r}\n{self.output()}"
        return r

    def fails(self, op: str, error: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]:
        """Send a command that must fail with the named error."""
        r = self.call(op, timeout, **kw)
        assert not r["ok"] and r["error"] == error, f"{op} {kw}: expected {error}, got {r}"
        return r

    def quit(self, timeout: float = 30.0) -> int:
        """Ask the component to stop; return its exit status."""
        if self.proc.poll() is None:
            self.send("quit")
        return self.wait(timeout)


def counter_json(writer: str, value: int) -> dict[str, Any]:
    """A cast.testing.Counter as protobuf JSON (int64 as a string, as JsonFormat prints it)."""
    return {"writer": writer, "value": str(value)}


# ------------------------------------------------------------------ RichEntry


def rich_entry(variant: str) -> Message:
    """The canonical cast.testing.RichEntry; the same values as cast.itest.Rich.canonical in Java."""
    from cast_fidelity_pb2 import SHADE_DARK, RichEntry

    P = RichEntry.Point
    R = RichEntry.Region
    e = RichEntry(
        text="Grüße, 世界 — ∑ 🚀 \u0000 end",
        blob=bytes([0, 0xFF, 0xFE, 0x80, 0x7F, 1]),
        int32_value=-(2**31),
        int64_min=-(2**63),
        int64_max=2**63 - 1,
        uint32_value=2**32 - 1,
        uint64_max=2**64 - 1,
        sint64_value=-(2**63 - 1),
        fixed64_value=2**64 - 2,
        sfixed64_value=-1234567890123456789,
        double_value=3.141592653589793,
        double_tiny=5e-324,
        double_huge=1.7976931348623157e308,
        double_infinity=-math.inf,
        float_value=0.1,
        flag=True,
        colour=RichEntry.COLOUR_BLUE,
        shade=SHADE_DARK,
        origin=P(x=1.5, y=-2.25, z=1e-10),
        region=R(
            label="Zürich",
            outline=[P(x=0, y=0, z=0), P(x=1, y=0, z=0)],
            colour=RichEntry.COLOUR_GREEN,
            attributes={"ключ": "значение", "a": ""},
            children=[R(label="child", colour=RichEntry.COLOUR_RED)],
        ),
        tags=["α", "", "tag"],  # noqa: RUF001 - a non-ASCII letter on purpose
        samples=[-(2**63), 0, 2**63 - 1, -1],
        weights=[0.5, -0.0, 1e300],
        colours=[RichEntry.COLOUR_RED, RichEntry.COLOUR_GREEN, RichEntry.COLOUR_BLUE, RichEntry.COLOUR_UNSPECIFIED],
        regions=[R(label="r1"), R(label="r2", attributes={"k": "v"})],
        counts={"a": 1, "negative": -5, "max": 2**63 - 1},
        points={-(2**63): P(x=1, y=2, z=3), 0: P(), 42: P(x=-1, y=-1, z=-1)},
        flags={True: "yes", False: "no"},
        maybe=0,
    )
    if variant == "circle":
        e.circle_radius = 2.5
    elif variant == "name":
        e.shape_name = "hexagon ⬡"
    elif variant == "polygon":
        e.polygon.CopyFrom(R(label="poly", outline=[P(x=1, y=1, z=0)]))
    else:
        raise ValueError(f"unknown RichEntry variant {variant}")
    return e


def _same(a: Any, b: Any) -> bool:
    # Floats compare by bits where it matters: -0.0 must stay -0.0.
    if isinstance(a, float) and isinstance(b, float):
        return a == b and math.copysign(1.0, a) == math.copysign(1.0, b)
    return bool(a == b)


def field_diffs(want: Message, got: Message) -> list[str]:
    """The names of the fields whose value or presence differ, compared one by one."""
    diffs = []
    for fd in want.DESCRIPTOR.fields:
        if fd.has_presence and want.HasField(fd.name) != got.HasField(fd.name):
            diffs.append(f"{fd.name} (presence)")
            continue
        w, g = getattr(want, fd.name), getattr(got, fd.name)
        if fd.is_repeated and not hasattr(w, "keys"):
            if len(w) != len(g) or not all(_same(x, y) for x, y in zip(w, g, strict=True)):
                diffs.append(fd.name)
        elif hasattr(w, "keys"):
            if dict(w) != dict(g):
                diffs.append(fd.name)
        elif not _same(w, g):
            diffs.append(fd.name)
    return diffs


# ------------------------------------------------------------------ cast run


def cast_run(config: Path, runtime_dir: Path, cwd: Path) -> RunningSystem:
    """``cast run CONFIG --no-status`` (the kit's run_system) in ``cwd``."""
    return run_system(config, cwd=cwd, directory=runtime_dir.parent, runtime_dir=runtime_dir)
