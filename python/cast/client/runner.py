"""Running a component: the launch contract (docs/design.md section 6) and the lifecycle.

Every component process gets ``CAST_ENDPOINT``, ``CAST_COMPONENT_ID``,
``CAST_SUBARCHITECTURE``, its token and ``CAST_ARGS`` (a JSON object), and
optionally ``CAST_TLS_*`` (see :mod:`cast.client.credentials`). The token is the
content of the file ``CAST_TOKEN_FILE`` when that is set (re-read when renewed),
else ``CAST_TOKEN``.
The runner connects, calls configure(args), start(), run(), and stop() once
on SIGINT/SIGTERM, on ``request_stop()``, or when run() raised.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from cast.client.channel import Backoff
from cast.client.component import Component
from cast.client.credentials import ClientTls, TokenSource, read_token_file
from cast.client.grpc_transport import GrpcTransport
from cast.client.transport import Transport
from cast.core.records import Identity
from cast.core.sessions import ComponentState
from cast.errors import CastError, InvalidArgumentError, UnavailableError
from cast.signals import dump_stacks_on_sigquit

__all__ = ["LaunchContract", "load_component_class", "main", "run_component"]

log = logging.getLogger("cast.run")

CONNECT_WINDOW_S = 20.0
"""How long a launched component keeps asking a server that does not answer before it gives up."""

CONNECT_RETRIED = ("UNAVAILABLE", "DEADLINE_EXCEEDED")
"""The failures of the first contact that are asked again: the server is down, still starting or busy.
Any other (a refused token, a bad TLS file) is the launch environment's fault and ends the runner at once."""


def connect_gave_up(endpoint: str, window: float, tls: bool, last: CastError) -> str:
    """What a runner says when no server answered its first contact within the connect window.

    The same words in C++ (cpp_client/src/connect_window.h) and Java (ConnectWindow.java).
    """
    spoken = "with TLS" if tls else "in plaintext"
    return (
        f"no CAST system answered at {endpoint} within {window:g} s (CAST_ENDPOINT, spoken to {spoken}): check "
        f"that the system is running and that CAST_ENDPOINT and CAST_TLS_* are its address and TLS settings "
        f"(last error: {last.message})"
    )


def connect_window_from(text: str) -> float:
    """``CAST_CONNECT_WINDOW_S`` as seconds (empty: the default); InvalidArgumentError for anything else."""
    if not text:
        return CONNECT_WINDOW_S
    try:
        seconds = float(text)
    except ValueError:
        seconds = -1.0
    if not 0 <= seconds < float("inf"):
        raise InvalidArgumentError(f"CAST_CONNECT_WINDOW_S {text!r}: give the seconds a launched component keeps "
                                   f"asking a server that does not answer, 0 or more (default {CONNECT_WINDOW_S:g})")
    return seconds


@dataclass(frozen=True)
class LaunchContract:
    """The environment a component process is started with."""

    endpoint: str
    component_id: str
    subarchitecture: str
    token: str
    args: dict[str, Any]
    tls: ClientTls | None = None  # CAST_TLS_CA / CAST_TLS_CERT / CAST_TLS_KEY / CAST_TLS_SERVER_NAME
    token_file: str = ""  # CAST_TOKEN_FILE: re-read when the orchestrator renews the token
    start_barrier: bool = False  # CAST_START_BARRIER=1: run() waits until every component has started
    connect_window: float = CONNECT_WINDOW_S  # CAST_CONNECT_WINDOW_S: how long the first contact is asked again

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> LaunchContract:
        """Read the contract; InvalidArgumentError naming every missing variable.

        The token is the file ``CAST_TOKEN_FILE`` names when that is set (the renewed one, so it wins over
        ``CAST_TOKEN``, as for ``cast.connect``); an empty or unreadable file is an error, not a fallback.
        """
        env = os.environ if env is None else env
        names = ("CAST_ENDPOINT", "CAST_COMPONENT_ID", "CAST_SUBARCHITECTURE")
        missing = [n for n in names if not env.get(n)]
        if not env.get("CAST_TOKEN") and not env.get("CAST_TOKEN_FILE"):
            missing.append("CAST_TOKEN or CAST_TOKEN_FILE")
        if missing:
            raise InvalidArgumentError(
                f"missing launch environment: {', '.join(missing)}; start the component with `cast run CONFIG`, "
                "or get the variables from `cast token`"
            )
        try:
            args = json.loads(env.get("CAST_ARGS") or "{}")
        except json.JSONDecodeError as exc:
            raise InvalidArgumentError(f"CAST_ARGS is not valid JSON: {exc}") from None
        if not isinstance(args, dict):
            raise InvalidArgumentError("CAST_ARGS must be a JSON object")
        token_file = env.get("CAST_TOKEN_FILE", "")
        return cls(
            env["CAST_ENDPOINT"],
            env["CAST_COMPONENT_ID"],
            env["CAST_SUBARCHITECTURE"],
            read_token_file(token_file) if token_file else env["CAST_TOKEN"],
            args,
            ClientTls.from_env(env),
            token_file,
            env.get("CAST_START_BARRIER", "") == "1",
            connect_window_from(env.get("CAST_CONNECT_WINDOW_S", "")),
        )

    def identity(self) -> Identity:
        """The identity the launch environment gives; the server's answer to Register completes it.

        Whether the component is privileged, and that the token really is for
        this id and SA, come from the server (cast.client.session), not from
        decoding the token here.
        """
        return Identity(self.component_id, self.subarchitecture, False)

    def connect(self, window: float = CONNECT_WINDOW_S) -> GrpcTransport:
        """A gRPC connection to the system.

        Whoever launched the component started the system first, so a server that does not
        answer at once is busy or still starting (a machine starting many components, or a server
        restarted by its supervisor): a first call failing with one of ``CONNECT_RETRIED`` is asked
        again with backoff for ``window`` seconds; then UnavailableError saying where it asked, for how
        long and what to check (the runner exits 2). Any other failure is raised at once.
        """
        tokens = TokenSource(self.token, self.token_file or None)
        deadline = time.monotonic() + window
        backoff = Backoff()
        while True:
            try:
                return GrpcTransport(self.endpoint, tokens, self.identity(), tls=self.tls)
            except CastError as err:
                if err.code not in CONNECT_RETRIED:
                    raise
                if time.monotonic() >= deadline:
                    raise UnavailableError(connect_gave_up(self.endpoint, window, self.tls is not None, err)) from None
                log.info("the server at %s is not answering yet (%s); asking again", self.endpoint, err.message)
                time.sleep(backoff.next())


def load_component_class(spec: str) -> type[Component]:
    """The class named by ``module:Class``; InvalidArgumentError saying what is wrong."""
    module_name, sep, class_name = spec.partition(":")
    if not sep or not module_name or not class_name:
        raise InvalidArgumentError(f"component class '{spec}' must be written module:Class")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise InvalidArgumentError(f"cannot import module '{module_name}' for component class '{spec}': {exc}") from exc
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Component)):
        raise InvalidArgumentError(
            f"'{spec}' is not a component class: it must subclass cast.UnmanagedComponent or cast.ManagedComponent"
        )
    return cls


class _Lifecycle:
    """Drives one component through configure, start, run and stop."""

    def __init__(
        self, component: Component, transport: Transport, args: dict[str, Any], barrier: bool,
        started: Callable[[], None] | None = None,
    ) -> None:
        self.component = component
        self.transport = transport
        self.args = args
        self.barrier = barrier
        self.started = started
        self.failed = False
        self._stopped = threading.Lock()
        self._stop_called = False
        component._cast_bind(transport)

    def stop(self) -> None:
        """Call stop() exactly once."""
        with self._stopped:
            if self._stop_called:
                return
            self._stop_called = True
        self.component._set_state(ComponentState.STOPPING)
        self.component.request_stop()
        try:
            self.component.stop()
        except Exception:
            log.exception("%s: stop() failed", self.component.component_id)
            self.failed = True

    def run(self) -> None:
        """configure, start, run; stop() on failure. Returns when run() returns or fails."""
        c = self.component
        try:
            c.configure(self.args)
            c.start()
            if self.barrier:
                # Watches made in start() are registered by now: say so, and run() only once every
                # component has, so none misses what another writes first (cast.core.barrier).
                c._set_state(ComponentState.STARTED)
                if not self.transport.await_run(c._stopping):
                    return  # asked to stop before the system got going: stop() follows, run() never ran
            c._set_state(ComponentState.RUNNING)
            self._say_started()
            c.run()
        except Exception:
            log.exception("%s failed", c.component_id)
            self.failed = True
            self.stop()
        finally:
            self._say_started()  # also when the lifecycle ended before run(): nobody waits forever

    def _say_started(self) -> None:
        started, self.started = self.started, None
        if started is not None:
            started()

    def close(self) -> None:
        self.component._cast_close()


def run_component(
    component: Component, transport: Transport, args: dict[str, Any], handle_signals: bool = True,
    barrier: bool = False, started: Callable[[], None] | None = None,
) -> int:
    """Run a component to the end; return the process exit code (0 ok, 1 failed).

    With ``barrier`` (a component `cast run` launched), run() waits after start()
    until every component of the system has started (cast.core.barrier).
    ``started`` is called once, on the lifecycle's thread, when run() is about to
    begin (start() returned: its watches are registered), or when the lifecycle
    ended before that (a hook failed, or the component was stopped first): what
    cast.testing waits for before it hands a running component to a test.

    run() executes on a worker thread so that a signal can call stop() while
    run() is busy; after run() returns the component keeps serving callbacks
    until it is asked to stop.
    """
    life = _Lifecycle(component, transport, args, barrier, started)
    signalled: list[int] = []
    if handle_signals:
        # The handler runs on the main thread, possibly while that thread holds the
        # lock of the stop Event (inside wait() or set()); setting the Event from
        # here would deadlock on a second signal. It only records the signal, which
        # the loop below turns into a stop from ordinary code.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda signum, _frame: signalled.append(signum))
    worker = threading.Thread(target=life.run, name=f"cast-run-{component.component_id}", daemon=True)
    worker.start()
    try:
        while not component.wait_for_stop(0.1):
            if signalled:
                break
            if not worker.is_alive() and life.failed:
                break
        life.stop()
        worker.join(10.0)
        if worker.is_alive():
            log.error("%s: run() did not return within 10 s of stop()", component.component_id)
            life.failed = True
        component.drain(5.0)
    finally:
        life.close()
    return 1 if life.failed else 0


def main(argv: list[str] | None = None) -> int:
    """``python -m cast.run module:Class``: run one component from the launch environment."""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or argv[0] in ("-h", "--help"):
        print("usage: python -m cast.run module:Class   "
              "(reads CAST_ENDPOINT, CAST_TOKEN_FILE or CAST_TOKEN, ... from the environment)")
        return 2
    logging.basicConfig(level=os.environ.get("CAST_LOG_LEVEL", "INFO"), format="%(asctime)s %(name)s: %(message)s")
    # A component that does not stop in time gets SIGQUIT before SIGKILL: its stacks go to its log.
    dump_stacks_on_sigquit()
    try:
        cls = load_component_class(argv[0])
        contract = LaunchContract.from_env()
        component = cls()
        transport = contract.connect(contract.connect_window)
        # Binding registers the session; a token for another component is refused here, naming both.
        return run_component(component, transport, contract.args, barrier=contract.start_barrier)
    except CastError as exc:
        print(f"cast.run: {exc.message}", file=sys.stderr)
        return 2
