"""``cast record``: every change of a running system's working memories into an MCAP file (docs/recording.md).

The system is found like the inspection commands find it (``--endpoint``,
``$CAST_ENDPOINT``, the running ``cast run``'s runtime directory). The
identity: a token made from ``--secret-file``, else ``$CAST_TOKEN_FILE`` or
``$CAST_TOKEN``, else one made from the system's secret, for ``cast-record``
(read-only) or ``cast-replay`` (privileged: whoever holds the secret may write
anywhere anyway); tokens made here do not expire, so a long recording can
resume after a reconnect.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Iterator, Mapping
from datetime import datetime
from pathlib import Path
from types import FrameType
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.text import Text

from cast.auth import TokenSigner
from cast.cli.connect import add_tls_options
from cast.client.credentials import ClientTls, TokenSource
from cast.client.discovery import NoSystemError, find_endpoint, find_secret, find_tls
from cast.core.records import Identity
from cast.errors import CastError, InvalidArgumentError
from cast.recording.channels import Gap
from cast.recording.mcap_file import RecordingWriter
from cast.recording.recorder import RECORD_ID, Recorder, RecordOptions, RecordStats
from cast.runtime_dir import RuntimeDir, default_runtime_dir
from cast.signals import silence, terminal_descriptors

__all__ = ["Reach", "add_commands", "add_connection_options", "reach", "stop_on_signals", "unreachable"]



class Reach:
    """Where a running system is and who this tool is there: endpoint, token, TLS, the identity told."""

    def __init__(self, endpoint: str, tokens: TokenSource, told: Identity, tls: ClientTls | None) -> None:
        self.endpoint = endpoint
        self.tokens = tokens
        self.told = told
        self.tls = tls


def reach(args: argparse.Namespace, component_id: str, privileged: bool,
          env: Mapping[str, str] | None = None) -> Reach:
    """The system and the tool's identity from the connection options and the environment."""
    env = os.environ if env is None else env
    runtime = RuntimeDir(Path(args.runtime_dir) if args.runtime_dir else default_runtime_dir(env))
    endpoint = find_endpoint(args.endpoint, runtime, env)
    tls = find_tls(args, runtime, env)
    if not args.secret_file and env.get("CAST_TOKEN_FILE"):
        return Reach(endpoint, TokenSource.from_file(env["CAST_TOKEN_FILE"]), Identity("", ""), tls)
    if not args.secret_file and env.get("CAST_TOKEN"):
        return Reach(endpoint, TokenSource(env["CAST_TOKEN"]), Identity("", ""), tls)
    who = Identity(component_id, "", privileged)
    token = TokenSigner(find_secret(args.secret_file, runtime, env)).issue(who)
    return Reach(endpoint, TokenSource(token), who, tls)


def unreachable(reach: Reach, error: CastError) -> CastError:
    """The error to show when the system does not answer: the one the inspection commands give."""
    if error.code == "UNAVAILABLE":
        return NoSystemError(f"no system answers at {reach.endpoint}: {error.message}")
    return error


@contextlib.contextmanager
def stop_on_signals(stop: threading.Event, why: list[str]) -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP set ``stop`` (and name themselves in ``why``) instead of interrupting.

    Restored after. SIGHUP (the terminal closed) first points the terminal's output at /dev/null.
    """
    terminals = terminal_descriptors()

    def handler(signum: int, _frame: FrameType | None) -> None:
        if signum == signal.SIGHUP:
            silence(terminals)
        if not why:
            why.append(signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def add_connection_options(p: argparse.ArgumentParser) -> None:
    """``--endpoint``, ``--runtime-dir``, ``--secret-file`` and the TLS options."""
    p.add_argument("--endpoint", help="directory HOST:PORT (default: $CAST_ENDPOINT, else the running `cast run`)")
    p.add_argument("--runtime-dir", help="runtime directory of the running `cast run` (default: $CAST_RUNTIME_DIR "
                                         "or .cast)")
    p.add_argument("--secret-file", help="token secret (default: $CAST_TOKEN, else $CAST_SECRET, else the runtime "
                                         "directory's)")
    add_tls_options(p)


# -------------------------------------------------------------------- status

def _mib(n: int) -> str:
    return f"{n / 1024 / 1024:.1f} MiB" if n >= 1024 * 1024 else f"{n / 1024:.1f} KiB"


class _Status:
    """The live line: changes, bytes, rate over the last seconds, gaps, connection."""

    def __init__(self, stats: RecordStats, target: str) -> None:
        self._stats = stats
        self._target = target
        self._samples: deque[tuple[float, int]] = deque(maxlen=20)  # 5 s at 4 refreshes a second
        self._began = time.monotonic()

    def __rich__(self) -> Text:
        now = time.monotonic()
        s = self._stats
        self._samples.append((now, s.changes))
        then, before = self._samples[0]
        rate = (s.changes - before) / (now - then) if now > then else 0.0
        line = (f"recording to {self._target}: {now - self._began:.0f} s, {s.changes} changes, {_mib(s.data_bytes)}, "
                f"{rate:.1f}/s")
        if s.gaps:
            line += f", {len(s.gaps)} gap{'s' if len(s.gaps) > 1 else ''}"
        if not s.connected:
            line += ", reconnecting"
        # One line however narrow the terminal: cropped, never wrapped.
        return Text(line, style="bold red" if s.gaps else "", no_wrap=True, overflow="ellipsis")


# -------------------------------------------------------------------- record

def _output(args: argparse.Namespace) -> Path:
    out = Path(args.output or datetime.now().strftime("cast-%Y%m%d-%H%M%S.mcap"))
    if out.exists():
        raise InvalidArgumentError(f"{out} exists: give another -o FILE, or remove it first (a recording is never "
                                   "overwritten)")
    if not out.parent.is_dir():
        raise InvalidArgumentError(f"cannot write {out}: no directory {out.parent}")
    return out


def _record(args: argparse.Namespace) -> int:
    if args.for_seconds is not None and args.for_seconds <= 0:
        raise InvalidArgumentError(f"--for {args.for_seconds}: give a number of seconds above 0")
    if args.from_revision < 0:
        raise InvalidArgumentError(f"--from-revision {args.from_revision}: revisions start at 1")
    out = _output(args)
    where = reach(args, RECORD_ID, privileged=False)
    options = RecordOptions(tuple(args.subarchitecture or ()), tuple(args.type or ()), args.from_revision)
    try:
        recorder = Recorder(where.endpoint, where.tokens, options, where.tls)
    except CastError as exc:
        raise unreachable(where, exc) from None
    console = Console(stderr=True, highlight=False)
    stop = threading.Event()
    why: list[str] = []
    writer: RecordingWriter | None = None
    try:
        try:
            recorder.start()
        except CastError as exc:
            raise unreachable(where, exc) from None
        writer = RecordingWriter(out, recorder.header())
        until = None if args.for_seconds is None else time.monotonic() + args.for_seconds

        def gap(g: Gap) -> None:
            console.print(f"cast record: {g.describe()}", style="bold red", soft_wrap=True)

        # Handlers first: a signal sent as soon as the line below is seen still finishes the file.
        with stop_on_signals(stop, why):
            console.print(f"cast record: recording {', '.join(recorder.subarchitectures)} of system "
                          f"'{recorder.system.name}' to {out} (Ctrl-C to stop)", soft_wrap=True)
            if console.is_terminal:
                with Live(_Status(recorder.stats, out.name), console=console, refresh_per_second=4,
                          transient=True):
                    recorder.run(writer, stop, until, gap)
            else:
                recorder.run(writer, stop, until, gap)
        recorder.stop_reason = why[0] if why else recorder.stop_reason
    finally:
        recorder.close()
        if writer is not None:
            writer.finish(recorder.trailer())
    return _summary(console, recorder, out, writer)


def _summary(console: Console, recorder: Recorder, out: Path, writer: RecordingWriter | None) -> int:
    stats = recorder.stats
    size = out.stat().st_size if out.exists() else 0
    per = ", ".join(f"{sa} {n}" for sa, n in stats.per_subarchitecture.items())
    console.print(f"cast record: {stats.changes} changes ({per}) in {out} ({_mib(size)}, "
                  f"{writer.messages if writer else 0} messages); stopped by {recorder.stop_reason or 'request'}",
                  soft_wrap=True)
    for key in recorder.channels.unregistered:
        console.print(f"cast record: no schema registered for {key[1]} in '{key[0]}': its values are recorded "
                      "without one (a viewer shows their bytes)", soft_wrap=True)
    if stats.gaps:
        console.print(f"cast record: the recording has {len(stats.gaps)} gap(s), marked on /cast/gaps (`cast info "
                      f"{out}` lists them): not every change is in it", style="bold red", soft_wrap=True)
        return 1
    return 0


def add_commands(sub: Any) -> None:
    """Add ``cast record``."""
    rec = sub.add_parser("record", help="record every change of the working memories to an MCAP file")
    rec.add_argument("-o", "--output", help="the file to write (default: cast-YYYYmmdd-HHMMSS.mcap here); "
                                            "never overwritten")
    rec.add_argument("--for", dest="for_seconds", type=float, help="stop after this many seconds (default: at "
                                                                   "Ctrl-C or SIGTERM)")
    rec.add_argument("--sa", dest="subarchitecture", action="append", help="SA to record (repeatable; default: all)")
    rec.add_argument("--type", action="append", help="only entries of this full message name (repeatable)")
    rec.add_argument("--from-revision", type=int, default=0,
                     help="start at this revision of each SA, as far as the server's history reaches (default: now)")
    add_connection_options(rec)
    rec.set_defaults(fn=_record)

