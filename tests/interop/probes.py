"""One driver interface over the C++ and the Java probe, so that a scenario is written once.

The C++ ``cast_probe`` takes positional string commands and answers
``{"ok", "result"}``; the Java ``cast.itest.Driven`` takes JSON commands with
named fields and answers flat objects. A scenario speaks the Java vocabulary
(``op`` plus keyword fields: ``id``, ``type``, ``value``, ``sa``,
``expected_version``, ``mode``, ``timeout_ms``, and for the streamed path
``prefix``, ``n``, ``size``); :class:`CppDriver` translates it into the C++
words. Watches differ more (named vs numbered, other filter syntax, a polled
error vs a ``watch_failed`` event), so they have methods of their own. Every
answer comes back flat, as Java gives it.
"""

from __future__ import annotations

import itertools
import time
from typing import Any, ClassVar, Protocol

from tests.interop.cpp_support import CppProbe
from tests.interop.java_support import JavaComponent, counter_json

COUNTER = "cast.testing.Counter"
__all__ = [
    "COUNTER", "DRIVERS", "CppDriver", "Driver", "JavaDriver", "address", "counter_json", "local_type", "run_script",
    "start", "vision_ops",
]


class Driver(Protocol):
    """What a scenario needs from a probe process, whatever its language."""

    lang: str
    max_pending_env: str

    def ready(self, timeout: float = 60.0) -> dict[str, Any]: ...
    def ok(self, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]: ...
    def fails(self, error: str, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]: ...
    def send(self, op: str, **kw: Any) -> Any: ...
    def pending(self, token: Any) -> bool: ...
    def answer(self, token: Any, timeout: float = 30.0) -> dict[str, Any]: ...
    def release(self, entry_id: str) -> int | None: ...
    def watch(self, filters: list[dict[str, Any]], gated: bool = False, **options: Any) -> Any: ...
    def watch_events(self, watch: Any, count: int = 0, timeout_ms: int = 0) -> list[dict[str, Any]]: ...
    def failure(self, watch: Any, within: float) -> dict[str, Any] | None: ...
    def active(self, watch: Any) -> bool | None: ...
    def quit(self, timeout: float = 30.0) -> int: ...
    def wait(self, timeout: float = 30.0) -> int: ...
    def close(self) -> None: ...
    def output(self) -> str: ...


# ------------------------------------------------------------------ filters

# Filters are written as Driven (Java) spells them; _cpp_filter respells them for cast_probe.
def vision_ops() -> list[dict[str, Any]]:
    """Every operation in the vision SA (the component's own)."""
    return [{"kind": "operation", "sa": "vision"}]


def local_type(type_name: str, include_entry: bool = False) -> list[dict[str, Any]]:
    """Changes of one type in the component's own SA."""
    return [{"kind": "local_type", "type": type_name, "include_entry": include_entry}]


def address(entry_id: str, include_entry: bool = False) -> list[dict[str, Any]]:
    """Changes of one entry in the component's own SA."""
    return [{"kind": "address", "id": entry_id, "include_entry": include_entry}]


def _cpp_filter(f: dict[str, Any]) -> dict[str, Any]:
    # The C++ probe says "local" for a type in the own SA, and "local" for the own SA of an
    # operation filter; every test component lives in vision.
    if f["kind"] == "local_type":
        out: dict[str, Any] = {"kind": "local", "type": f["type"]}
    elif f["kind"] == "address":
        out = {"kind": "address", "id": f["id"]}
    elif f["kind"] == "operation":
        sa = "local" if f.get("sa") == "vision" else f["sa"]
        out = {"kind": "operation", "ops": f.get("operations", []), "sa": sa}
    else:
        raise ValueError(f"no C++ spelling for filter {f}")
    if f.get("include_entry"):
        out["include_entry"] = True
    return out


# ------------------------------------------------------------------ C++


class CppDriver(CppProbe):
    """``cast_probe`` behind the shared vocabulary."""

    lang = "cpp"
    max_pending_env = "CAST_PROBE_MAX_PENDING"
    _names: ClassVar[itertools.count[int]] = itertools.count(1)

    def ready(self, timeout: float = 60.0) -> dict[str, Any]:
        """Wait until the probe is connected and started."""
        return super().ready(timeout)

    @staticmethod
    def words(op: str, kw: dict[str, Any]) -> list[Any]:
        """The C++ command line of a shared command ("-" for the own SA and for no expectation)."""
        sa = kw.get("sa") or "-"
        expected = "-" if kw.get("expected_version") is None else kw["expected_version"]
        timeout = "-" if kw.get("timeout_ms") is None else kw["timeout_ms"]
        table: dict[str, list[Any]] = {
            "add": ["add", kw.get("type"), kw.get("id"), sa, kw.get("value")],
            "overwrite": ["overwrite", kw.get("type"), kw.get("id"), sa, expected, kw.get("value")],
            "get": ["get", kw.get("type"), kw.get("id"), sa],
            "get_all": ["getall", kw.get("type"), sa, 0],
            "exists": ["exists", kw.get("id"), sa],
            "delete": ["delete", kw.get("id"), sa, expected],
            "lock": ["lock", kw.get("id"), kw.get("mode"), sa, timeout],
            "try_lock": ["trylock", kw.get("id"), kw.get("mode"), sa],
            "unlock": ["unlock", kw.get("id"), sa],
            "report": ["report", kw.get("name"), kw.get("value")],
            "add_async": ["addasync", kw.get("prefix"), kw.get("n")],
            "overwrite_async": ["overwriteasync", kw.get("id"), kw.get("n")],
            "big_write": ["bigwrite", kw.get("id"), sa, kw.get("size")],
            "big_read": ["bigread", kw.get("id"), sa],
            "open_gate": ["open_gate"],
            "whoami": ["whoami"],
            "new_id": ["newid"],
            "ping": ["ping"],
            "quit": ["quit"],
        }
        return table[op]

    def call(self, *words: Any, timeout: float = 30.0) -> dict[str, Any]:
        """Send a command in C++ words (``send`` takes shared ones here) and return its answer."""
        CppProbe.send(self, *words)
        return self.next_json(timeout)

    def ok(self, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]:  # type: ignore[override]
        """Send a shared command that must succeed; its result."""
        return super().ok(*self.words(op, kw), timeout=timeout)

    def fails(self, error: str, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]:  # type: ignore[override]
        """Send a shared command that must fail with ``error``; the answer."""
        return super().fails(error, *self.words(op, kw), timeout=timeout)

    def send(self, op: str, **kw: Any) -> None:  # type: ignore[override]
        """Send a shared command without waiting; the probe answers in order, so no token is needed."""
        super().send(*self.words(op, kw))

    def pending(self, token: Any) -> bool:
        """Whether the answer to the command sent last has not come yet."""
        return self.lines.empty()

    def answer(self, token: Any, timeout: float = 30.0) -> dict[str, Any]:
        """The next answer, flattened as Java gives it."""
        r = self.next_json(timeout)
        return {"ok": True, **r["result"]} if r["ok"] else r

    def release(self, entry_id: str) -> int | None:
        """Drop one lock level by letting a guard go out of scope (RAII unlock); the probe does not say
        what depth remains (None)."""
        super().ok("release", entry_id, "-")
        return None

    def watch(self, filters: list[dict[str, Any]], gated: bool = False, **options: Any) -> str:
        """Start a watch; its name. ``options``: ``delivery``, ``priority``, ``slow_ms`` (a callback that sleeps)."""
        name = f"w{next(self._names)}"
        spec: dict[str, Any] = {"filters": [_cpp_filter(f) for f in filters], **options}
        if gated:
            spec["gated"] = True
        super().ok("watch", name, spec)
        return name

    def watch_events(self, watch: Any, count: int = 0, timeout_ms: int = 0) -> list[dict[str, Any]]:
        """The events of a watch so far, waiting up to ``timeout_ms`` for ``count`` of them."""
        events: list[dict[str, Any]] = self._events(watch, count, timeout_ms)["events"]
        return events

    def _events(self, watch: Any, count: int, timeout_ms: int) -> dict[str, Any]:
        return super().ok("events", watch, count, timeout_ms, timeout=timeout_ms / 1000 + 10)

    def failure(self, watch: Any, within: float) -> dict[str, Any] | None:
        """How the watch failed (``{"error": name}``), polling up to ``within`` seconds; None if it did not."""
        deadline = time.monotonic() + within
        while True:
            error = self._events(watch, 0, 0)["error"]
            if error:
                return {"error": error}
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.1)

    def active(self, watch: Any) -> bool | None:
        """Unknown: the C++ probe reports activity only when cancelling."""
        return None


# ------------------------------------------------------------------ Java


class JavaDriver(JavaComponent):
    """``cast.itest.Driven`` behind the shared vocabulary (which is its own)."""

    lang = "java"
    max_pending_env = "DRIVEN_MAX_PENDING"

    def fails(self, error: str, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]:  # type: ignore[override]
        """Send a command that must fail with ``error`` (the argument order of CppProbe.fails)."""
        return super().fails(op, error, timeout, **kw)

    def send(self, op: str, **kw: Any) -> int:
        """Send a command without waiting; its sequence number."""
        return super().send(op, **{k: v for k, v in kw.items() if v is not None})

    def ok(self, op: str, timeout: float = 30.0, **kw: Any) -> dict[str, Any]:
        """Send a command that must succeed (fields set to None are left out)."""
        return super().ok(op, timeout, **{k: v for k, v in kw.items() if v is not None})

    def pending(self, token: Any) -> bool:
        """Whether command ``token`` is still unanswered."""
        return token not in self.replies

    def answer(self, token: Any, timeout: float = 30.0) -> dict[str, Any]:
        """The answer to command ``token``."""
        return self.reply(token, timeout)

    def release(self, entry_id: str) -> int | None:
        """Drop one lock level (Java has no guard objects to drop: an explicit unlock); the depth left."""
        depth: int = self.ok("unlock", id=entry_id)["depth"]
        return depth

    def watch(self, filters: list[dict[str, Any]], gated: bool = False, **options: Any) -> int:
        """Start a watch; its number. ``options``: ``delivery``, ``priority``, ``slow_ms`` (a callback that sleeps)."""
        spec = [{k: v for k, v in f.items() if v not in (None, False)} for f in filters]
        watch: int = self.ok("watch", filters=spec, gated=gated or None, **options)["watch"]
        return watch

    def watch_events(self, watch: Any, count: int = 0, timeout_ms: int = 0) -> list[dict[str, Any]]:
        """The events of a watch so far, waiting up to ``timeout_ms`` for ``count`` of them."""
        stats = self.ok("watch_stats", watch=watch, expected=count, timeout_ms=timeout_ms,
                        timeout=timeout_ms / 1000 + 10)
        events: list[dict[str, Any]] = stats["events"]
        return events

    def failure(self, watch: Any, within: float) -> dict[str, Any] | None:
        """The ``watch_failed`` event (error and message) if one comes within ``within`` seconds."""
        try:
            return self.wait_event("watch_failed", timeout=within)
        except AssertionError:
            return None

    def active(self, watch: Any) -> bool | None:
        """Whether the watch is still active."""
        active: bool = self.ok("watch_stats", watch=watch)["active"]
        return active


DRIVERS: dict[str, type[CppDriver] | type[JavaDriver]] = {"cpp": CppDriver, "java": JavaDriver}


def start(lang: str, env: dict[str, str]) -> Driver:
    """Start the probe of ``lang`` with the launch environment ``env`` (not waiting for it to be ready)."""
    return DRIVERS[lang](env)


def run_script(lang: str, env: dict[str, str], commands: list[dict[str, Any]]) -> tuple[int, list[dict[str, Any]], str]:
    """Start a probe, run ``commands`` (``{"op": ..., **fields}``), stop it; (exit status, answers, output).

    With no commands the probe is only expected to fail to start: its exit status and output say why.
    """
    probe = start(lang, env)
    try:
        answers: list[dict[str, Any]] = []
        if commands:
            try:
                probe.ready(30)
            except AssertionError:  # it could not connect: the status and output say why
                return probe.wait(30), [], probe.output()
            for command in commands:
                fields = dict(command)
                answers.append(probe.answer(probe.send(fields.pop("op"), **fields)))
            status = probe.quit(30)
        else:
            if isinstance(probe, CppDriver):
                # EOF on stdin: a C++ probe that did connect would stop at once.
                assert probe.proc.stdin is not None
                try:
                    probe.proc.stdin.close()
                except BrokenPipeError:
                    pass
            status = probe.wait(60)
        time.sleep(0.1)  # let the reader threads collect the last lines
        return status, answers, probe.output()
    finally:
        probe.close()
