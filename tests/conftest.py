"""Shared fixtures: real servers on port 0, tokens, test entry types, component processes."""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, settings

ROOT = Path(__file__).resolve().parent.parent

# Property tests assert properties, not times: hypothesis's default 200 ms deadline per example failed
# them on a loaded machine. Its too-slow health check likewise.
settings.register_profile("cast", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("cast")

VENV_BIN = Path(sys.executable).parent
SECRET = "test-secret-0123456789abcdef-0123456789"

# Generate the test entry types once per session, into a directory that is on
# sys.path here and on PYTHONPATH for component processes.
_GEN_DIR = Path(tempfile.mkdtemp(prefix="cast-test-gen-"))
atexit.register(shutil.rmtree, _GEN_DIR, ignore_errors=True)
subprocess.run(
    [
        sys.executable,
        "-m",
        "grpc_tools.protoc",
        f"-I{ROOT / 'tests' / 'protos'}",
        f"--python_out={_GEN_DIR}",
        *[str(p) for p in sorted((ROOT / "tests" / "protos").glob("*.proto"))],
    ],
    check=True,
)
sys.path.insert(0, str(_GEN_DIR))
# Test component modules live in tests/components.
sys.path.insert(0, str(ROOT / "tests" / "components"))

from cast.auth import TokenSigner  # noqa: E402
from cast.client.component import Component  # noqa: E402
from cast.client.grpc_transport import GrpcTransport  # noqa: E402
from cast.core.records import Identity  # noqa: E402
from cast.testing import wait_for as kit_wait_for  # noqa: E402
from tests.durations import Recorder, longest_files_first  # noqa: E402

GEN_DIR = _GEN_DIR
# CAST_TEST_INSTALLED=1: the processes import the cast of the running interpreter (a compiled wheel), not the tree's.
PYTHONPATH = os.pathsep.join([str(_GEN_DIR), str(ROOT / "tests" / "components"),
                              *([] if os.environ.get("CAST_TEST_INSTALLED") == "1" else [str(ROOT / "python")])])


# Markers by folder (pyproject.toml lists them); "namespaces" goes to the tests of modules that use
# tests/netns.py, wherever they live.
_FOLDER_MARKERS = {"interop": "interop", "web": "browser", "bench": "bench", "packaging": "packaging", "ros": "ros"}


def pytest_addoption(parser: pytest.Parser) -> None:
    """``--compiled-run-has PATH``: the tests under PATH run against the compiled build instead (make test)."""
    parser.addoption(
        "--compiled-run-has", action="append", default=[], metavar="PATH",
        help="leave out the tests under PATH (a folder or file under the checkout) that the compiled build's run "
             "takes (make test runs them there, beside this run); those marked incompatible_with_mypyc stay here")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark each test with what it needs beyond the Python environment; the longest files first; leave out
    the tests the compiled build's run takes (``--compiled-run-has``: deselected, and named in the summary)."""
    elsewhere = [(ROOT / p).resolve() for p in config.getoption("compiled_run_has")]
    missing = [str(p) for p in elsewhere if not p.exists()]
    if missing:
        raise pytest.UsageError(f"--compiled-run-has names no test folder or file: {missing}; give paths under {ROOT}")
    if elsewhere:
        left = [i for i in items if any(i.path.is_relative_to(p) for p in elsewhere)
                and not i.get_closest_marker("incompatible_with_mypyc")]
        if left:
            config.hook.pytest_deselected(items=left)
            taken = set(map(id, left))
            items[:] = [i for i in items if id(i) not in taken]
    longest_files_first(items)
    for item in items:
        parts = item.path.relative_to(ROOT / "tests").parts
        if len(parts) > 1 and parts[0] in _FOLDER_MARKERS:
            item.add_marker(_FOLDER_MARKERS[parts[0]])
        module = getattr(item, "module", None)
        if module is not None and any(getattr(v, "__module__", None) == "tests.netns" for v in vars(module).values()):
            item.add_marker("namespaces")

_RECORDER = Recorder()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Each phase's seconds, for the order of the next run (tests/durations.py)."""
    _RECORDER.add(report)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Write the seconds per file of a whole run (tests/durations.py); only the xdist controller has them all."""
    if not hasattr(session.config, "workerinput"):
        _RECORDER.write(session)


def pytest_terminal_summary(terminalreporter: Any, config: pytest.Config) -> None:
    """Where the tests left to the compiled build went (``--compiled-run-has``; under xdist the summary
    does not count them); each rerun test's first failure, shortened: `-rR` names the test only, and a
    rerun is a defect to fix."""
    elsewhere = config.getoption("compiled_run_has")
    if elsewhere:
        terminalreporter.write_line(f"left to the compiled build's run (make test-mypyc): {' '.join(elsewhere)}")
    reruns = terminalreporter.stats.get("rerun", [])
    if not reruns:
        return
    terminalreporter.section("first failures of the rerun tests")
    for report in reruns:
        text = str(getattr(report, "longreprtext", "") or report.longrepr or "").strip().splitlines()
        terminalreporter.write_line(f"{report.nodeid} ({report.when}):")
        for line in text[-25:]:  # the end of a traceback says what failed
            terminalreporter.write_line(f"    {line}")

@dataclass
class ServerHandle:
    """A `cast serve` process on a free port."""

    process: subprocess.Popen[str]
    endpoint: str
    config_path: Path
    signer: TokenSigner = field(default_factory=lambda: TokenSigner(SECRET.encode()))
    log_lines: list[str] = field(default_factory=list)

    def token(self, component_id: str, sa: str, privileged: bool = False) -> str:
        """A valid token for a component."""
        return self.signer.issue(Identity(component_id, sa, privileged))

    def env(
        self, component_id: str, sa: str, privileged: bool = False, args: dict[str, Any] | None = None,
        token_file: Path | None = None,
    ) -> dict[str, str]:
        """The launch environment of a component process.

        With ``token_file`` the token is written there (on a line of its own, as ``cast token --write`` and
        ``cast run`` write it) and given as ``CAST_TOKEN_FILE`` alone, as ``cast export`` launches components.
        """
        env = dict(os.environ)
        token = self.token(component_id, sa, privileged)
        env.update(
            CAST_ENDPOINT=self.endpoint,
            CAST_COMPONENT_ID=component_id,
            CAST_SUBARCHITECTURE=sa,
            CAST_ARGS=json.dumps(args or {}),
            PYTHONPATH=PYTHONPATH,
        )
        if token_file is None:
            env["CAST_TOKEN"] = token
        else:
            token_file.write_text(f"\n{token}\n")
            env.pop("CAST_TOKEN", None)
            env["CAST_TOKEN_FILE"] = str(token_file)
        return env

    def connect(
        self, component_id: str, sa: str, privileged: bool = False, cls: type[Component] | None = None
    ) -> Component:
        """A component object in the test process, bound over gRPC (close with .close())."""
        from cast import UnmanagedComponent

        component = (cls or UnmanagedComponent)()
        identity = Identity(component_id, sa, privileged)
        component._cast_bind(GrpcTransport(self.endpoint, self.token(component_id, sa, privileged), identity))
        return component

    def spawn(
        self, spec: str, component_id: str, sa: str, privileged: bool = False, args: dict[str, Any] | None = None
    ) -> subprocess.Popen[str]:
        """Start `python -m cast.run spec` as a separate process."""
        return subprocess.Popen(
            [sys.executable, "-m", "cast.run", spec],
            env=self.env(component_id, sa, privileged, args),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )

    def components(self) -> dict[str, Any]:
        """The components this server knows, by id (ComponentInfo from the directory)."""
        return components(self.endpoint, self.token("tool", "vision"))

    def stop(self) -> None:
        """Stop the server (SIGTERM, then SIGKILL)."""
        stop_process(self.process, 10)


def run_to_end(
    command: list[str], what: str, timeout: float, *, cwd: Path | None = None, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """Run ``command`` in a session of its own to its end; one still running after ``timeout`` fails the test.

    Before it is killed, the session gets SIGQUIT, on which the Python runner and `cast` print every
    thread's stack (cast.signals) and the JVM its thread dump (bash ignores it): the test fails with
    what ``what`` printed and where it hung.
    """
    proc = subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGQUIT)
        time.sleep(1.0)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        raise AssertionError(f"{what} did not end within {timeout:g} s; it printed:\n{out}\n"
                             f"and on stderr (with the stacks of its threads):\n{err}") from None
    return subprocess.CompletedProcess(command, proc.returncode, out, err)


def stop_process(process: subprocess.Popen[str], grace: float) -> None:
    """SIGTERM a test's child process if it still runs, SIGKILL after ``grace`` seconds; wait for its end."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(grace)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def components(endpoint: str, token: str) -> dict[str, Any]:
    """The components the server at ``endpoint`` knows, by id (ComponentInfo from the directory)."""
    import grpc

    from cast.v1 import directory_pb2, directory_pb2_grpc

    with grpc.insecure_channel(endpoint) as channel:
        desc = directory_pb2_grpc.DirectoryStub(channel).DescribeSystem(
            directory_pb2.DescribeSystemRequest(), metadata=(("authorization", f"Bearer {token}"),), timeout=10
        )
    return {c.id: c for c in desc.components}


def wait_for(condition: Callable[[], Any], timeout: float = 60.0, what: str = "condition") -> Any:
    """cast.testing.wait_for with this suite's longer guard (a busy 2-core machine): ``condition()``'s first
    true value; a failure after ``timeout`` seconds says what it returned, or what it asserted, last.

    The timeout is a guard against a hang, not a measurement: tests assert no wall-clock times.
    """
    return kit_wait_for(condition, timeout, what)


class OnAThread:
    """A call running on a thread of its own (a lock that waits, say); what it raised is kept for the test."""

    def __init__(self, call: Callable[[], object]) -> None:
        self._call = call
        self._error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self._call()
        except BaseException as exc:  # the test looks at it
            self._error = exc

    def raised(self, timeout: float = 60.0) -> BaseException | None:
        """What the call raised (None: it returned), once it ended; fails the test if it is still running."""
        self.thread.join(timeout)
        assert not self.thread.is_alive(), f"the call on its thread did not end within {timeout:g} s"
        return self._error


def maven() -> list[str]:
    """The tests' Maven command: ``$CAST_TEST_MVN`` (the Makefile's MVN, say with a local repository of its
    own), else ``mvn -B -ntp``."""
    return shlex.split(os.environ.get("CAST_TEST_MVN") or "mvn -B -ntp")


def maven_repository() -> Path:
    """The local Maven repository that command installs into and reads from."""
    for word in maven():
        if word.startswith("-Dmaven.repo.local="):
            return Path(word.split("=", 1)[1])
    return Path.home() / ".m2" / "repository"


def register_session(channel: Any, metadata: Any) -> str:
    """Register a session for a raw-stub caller, as every client library does before it locks or proposes.

    The session lives for the server's lease (10 s by default) without heartbeats: enough for a test's calls.
    """
    from cast.v1 import directory_pb2, directory_pb2_grpc

    request = directory_pb2.RegisterRequest(language="raw", kind="unmanaged", pid=os.getpid(), host="test")
    return str(directory_pb2_grpc.DirectoryStub(channel).Register(request, metadata=metadata, timeout=10).session_id)


def start_server(tmp: Path, config: dict[str, Any], extra_args: list[str] | None = None) -> ServerHandle:
    """Write ``config`` as YAML and start `cast serve` on port 0; wait for its first line."""
    tmp.mkdir(parents=True, exist_ok=True)
    config_path = tmp / "system.yaml"
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    return serve(config_path, cwd=tmp, extra=tuple(extra_args or ()))


def serve(
    config_path: Path, listen: str = "127.0.0.1:0", env: dict[str, str] | None = None, cwd: Path | None = None,
    extra: tuple[str, ...] = (), own_session: bool = False,
) -> ServerHandle:
    """Start `cast serve CONFIG [EXTRA...]` and wait for its `listening on` line.

    ``own_session`` puts the server in its own process group, for tests that signal the group.
    """
    full_env = dict(os.environ, CAST_SECRET=SECRET, PYTHONPATH=PYTHONPATH, **(env or {}))
    proc = subprocess.Popen(
        [str(VENV_BIN / "cast"), "serve", str(config_path), "--listen", listen, *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=full_env,
        cwd=cwd or config_path.parent,
        start_new_session=own_session,
    )
    assert proc.stdout is not None
    first = proc.stdout.readline().strip()
    if not first.startswith("listening on "):
        proc.kill()
        raise RuntimeError(f"server did not start: {first}\n{proc.stdout.read()}")
    handle = ServerHandle(proc, first.removeprefix("listening on "), config_path)

    def drain() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            handle.log_lines.append(line)

    threading.Thread(target=drain, daemon=True).start()
    return handle


DEFAULT_CONFIG: dict[str, Any] = {
    "system": "test",
    "subarchitectures": {"vision": {}, "language": {}, "motor": {}},
}


@pytest.fixture
def server(tmp_path: Path) -> Iterator[ServerHandle]:
    """A real server hosting vision, language and motor (task managers: always)."""
    handle = start_server(tmp_path, DEFAULT_CONFIG)
    yield handle
    handle.stop()


@pytest.fixture
def server_factory(tmp_path: Path) -> Iterator[Any]:
    """Start servers with custom configurations; all are stopped at the end."""
    started: list[ServerHandle] = []

    def make(config: dict[str, Any], extra_args: list[str] | None = None) -> ServerHandle:
        handle = start_server(tmp_path / f"server{len(started)}", config, extra_args)
        started.append(handle)
        return handle

    yield make
    for handle in started:
        handle.stop()


@pytest.fixture
def pki(tmp_path: Path) -> dict[str, Path]:
    """A CA with server and client certificates, and an unrelated CA, made for this test (TLS suites)."""
    from tests.reliability.certs import make_pki  # cryptography is needed only by the TLS tests

    return make_pki(tmp_path)


@contextmanager
def renewing_token_file(signer: TokenSigner, identity: Identity, path: Path, ttl: float = 2.0) -> Iterator[Path]:
    """A token file for ``identity`` rewritten every 0.5 s with a fresh ``ttl``-second token, as the
    orchestrator renews launched components' tokens (cast.orchestrator.security), until the block ends."""
    path.write_text(signer.issue(identity, ttl_seconds=ttl))
    stop = threading.Event()

    def renewer() -> None:
        while not stop.wait(0.5):
            tmp = path.with_suffix(".tmp")
            tmp.write_text(signer.issue(identity, ttl_seconds=ttl))
            tmp.replace(path)  # readers see the old token or the new one, never half a file

    thread = threading.Thread(target=renewer, daemon=True)
    thread.start()
    try:
        yield path
    finally:
        stop.set()
        thread.join(5)
