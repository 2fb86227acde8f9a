"""The server with components as separate processes: the guarantees end to end."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest
from cast_testing_pb2 import Counter, Pose

import cast
from cast.v1 import directory_pb2
from tests.conftest import ServerHandle, wait_for


def finish(proc, timeout: float = 60.0) -> str:  # type: ignore[no-untyped-def]
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out
    return out


def test_many_writers_in_several_sas_one_watcher_sees_every_event_once_in_order(server: ServerHandle) -> None:
    watcher = server.connect("watcher", "language")
    events: list[cast.WorkingMemoryChange] = []
    watcher.on_change(cast.global_type_filter(Counter), events.append)
    writers = [
        server.spawn("itest_components:Writer", f"w-{sa}-{i}", sa, args={"count": 40})
        for sa in ("vision", "language", "motor")
        for i in range(2)
    ]
    for proc in writers:
        finish(proc)
    expected_per_writer = 40 + 40 + len(range(0, 40, 3))  # adds, overwrites, deletes
    wait_for(lambda: len(events) >= 6 * expected_per_writer, what="all events")
    watcher.drain(5)
    time.sleep(0.2)
    assert len(events) == 6 * expected_per_writer  # nothing twice
    by_sa: dict[str, list[int]] = defaultdict(list)
    for ev in events:
        by_sa[ev.subarchitecture].append(ev.revision)
    for sa, revisions in by_sa.items():
        # every write of each WM, in revision order, with no gap
        assert revisions == list(range(1, len(revisions) + 1)), sa
        assert len(revisions) == 2 * expected_per_writer
    per_writer: dict[str, int] = defaultdict(int)
    for ev in events:
        per_writer[ev.source_component] += 1
    assert set(per_writer.values()) == {expected_per_writer}
    watcher._cast_close()


def test_cross_sa_reads(server: ServerHandle) -> None:
    vision = server.connect("seg", "vision")
    for label in ("cube", "ball"):
        vision.add(vision.new_id(), Pose(label=label))
    finish(server.spawn("itest_components:CrossReader", "reader", "language", args={"source": "vision"}))
    summary = vision.get("summary", Pose, subarchitecture="language")
    assert summary.label == "ball,cube"
    vision._cast_close()


def test_privileged_writes_another_sa_while_unprivileged_is_refused(server: ServerHandle) -> None:
    finish(server.spawn("itest_components:Intruder", "intruder", "language", args={"target": "vision"}))
    finish(server.spawn("itest_components:Intruder", "boss", "language", privileged=True, args={"target": "motor"}))
    reader = server.connect("reader", "motor")
    refused = reader.get("outcome-intruder", Pose, subarchitecture="language").label
    assert refused.startswith("refused: component 'intruder' (SA 'language') may not add in subarchitecture 'vision'")
    assert reader.get("outcome-boss", Pose, subarchitecture="language").label == "written"
    assert reader.get("goal", Pose, subarchitecture="motor").label == "from boss"
    assert not reader.exists("goal", subarchitecture="vision")
    reader._cast_close()


def test_managed_component_task_is_adopted_through_the_task_manager(server: ServerHandle) -> None:
    finish(server.spawn("itest_components:Proposer", "proposer", "vision"))
    reader = server.connect("reader", "vision")
    adopted = [e for e in reader.get_all(Pose) if e.id.startswith("adopted-")]
    assert len(adopted) == 1
    assert adopted[0].value.label == "cube" and list(adopted[0].value.tags) == ["recognise"]
    reader._cast_close()


def test_sigterm_calls_the_stop_hook(server: ServerHandle) -> None:
    proc = server.spawn("itest_components:StopRecorder", "recorder", "vision")
    reader = server.connect("reader", "vision")
    wait_for(lambda: reader.exists("started"), what="component start")
    proc.send_signal(signal.SIGTERM)
    finish(proc)
    assert reader.get("stopped", Pose).label == "stop hook ran"
    reader._cast_close()


def test_a_killed_components_locks_are_released(server: ServerHandle) -> None:
    proc = server.spawn("itest_components:Crasher", "crasher", "vision")
    other = server.connect("other", "vision")
    wait_for(lambda: other.exists("ready"), what="crasher ready")
    with pytest.raises(cast.LockedError, match="locked \\(ODR\\) by component 'crasher'"):
        other.get("held", Pose)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    # The heartbeat stream breaks with the process, ending the session and its locks.
    with other.lock("held", cast.LockMode.O, timeout=30):
        assert other.get("held", Pose).label == "locked by a crasher"
    other._cast_close()


def test_forged_and_missing_tokens_are_unauthenticated(server: ServerHandle) -> None:
    import grpc

    from cast.auth import TokenSigner
    from cast.client.grpc_transport import GrpcTransport
    from cast.core.records import Identity
    from cast.v1 import entry_pb2, working_memory_pb2, working_memory_pb2_grpc

    forged = TokenSigner(b"not-the-system-secret-0000000000000000").issue(Identity("evil", "vision", True))
    with pytest.raises(cast.UnauthenticatedError, match="signature does not match"):
        GrpcTransport(server.endpoint, forged, Identity("evil", "vision", True))
    channel = grpc.insecure_channel(server.endpoint)
    stub = working_memory_pb2_grpc.WorkingMemoryStub(channel)
    req = working_memory_pb2.GetRequest(address=entry_pb2.EntryAddress(id="x", subarchitecture="vision"))
    with pytest.raises(grpc.RpcError) as info:
        stub.Get(req, timeout=10)
    assert info.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert "no token" in info.value.details()
    channel.close()


def test_in_process_component_under_cast_serve(server_factory) -> None:  # type: ignore[no-untyped-def]
    handle = server_factory(
        {
            "system": "inproc",
            "subarchitectures": {
                "vision": {
                    "components": {
                        "inside": {"class": "itest_components:Writer", "in_process": True, "args": {"count": 5}},
                    }
                },
                "language": {},
            },
        }
    )
    reader = handle.connect("reader", "language")
    wait_for(lambda: len(reader.get_all(Counter, subarchitecture="vision")) == 3, what="in-process writes")
    entries = reader.get_all(Counter, subarchitecture="vision")
    # Each was added, then overwritten once with the version its add returned (the Writer checks it).
    assert {e.author for e in entries} == {"inside"} and len({e.version for e in entries}) == 1
    reader._cast_close()


def test_a_signal_during_signal_handling_does_not_deadlock(server: ServerHandle) -> None:
    proc = server.spawn("itest_components:SignalUnderLock", "signalled", "vision")
    try:
        finish(proc, timeout=30)  # a handler that takes the stop event's lock never returns
    finally:
        proc.kill()
    reader = server.connect("reader", "vision")
    assert reader.get("handled", Pose).label == "the handler returned"
    reader._cast_close()


def test_the_directory_shows_a_component_running_as_soon_as_its_run_begins(server_factory) -> None:  # type: ignore[no-untyped-def]
    # A lease of 60 s: the next regular heartbeat would come 20 s later; the state is reported at once.
    handle = server_factory({"system": "states", "subarchitectures": {"vision": {}}}, ["--lease-ms", "60000"])
    proc = handle.spawn("itest_components:Announcer", "announcer", "vision")
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "RUNNING"
        reader = handle.connect("reader", "vision")
        try:
            def state() -> str:
                desc = reader._transport.describe()
                info = next(c for c in desc.components if c.id == "announcer")
                return directory_pb2.ComponentState.Name(info.state)

            wait_for(lambda: state() == "COMPONENT_STATE_RUNNING", timeout=10, what="RUNNING in the directory")
        finally:
            reader._cast_close()
    finally:
        proc.terminate()
        proc.wait(10)


def test_the_server_says_who_a_component_is_and_a_launch_environment_that_disagrees_stops_it(
    server: ServerHandle,
) -> None:
    import subprocess
    import sys

    env = server.env("writer", "vision")
    env["CAST_COMPONENT_ID"] = "somebody-else"  # the token is for 'writer'
    done = subprocess.run([sys.executable, "-m", "cast.run", "itest_components:Writer"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "the token is for component 'writer' in SA 'vision'" in done.stderr
    assert "told component 'somebody-else' in SA 'vision'" in done.stderr
    # A privileged token makes a privileged component, as the server says (the client decodes nothing).
    from cast.client.grpc_transport import GrpcTransport
    from cast.core.records import Identity

    boss = cast.UnmanagedComponent()
    told = Identity("boss", "vision", False)  # what a launch environment can say: no privilege flag
    boss._cast_bind(GrpcTransport(server.endpoint, server.token("boss", "vision", privileged=True), told))
    try:
        assert boss.privileged
        boss.add("from-boss", Counter(), subarchitecture="language")
    finally:
        boss._cast_close()


def test_a_launched_component_waits_for_a_server_that_answers_late(server: ServerHandle, tmp_path) -> None:  # type: ignore[no-untyped-def]
    # The launcher started the system first, so a server that does not answer at once is busy or still
    # starting: the component asks again (cast.client.runner.LaunchContract.connect) instead of exiting 2.
    import socket

    from tests.conftest import serve

    with socket.socket() as probe:  # a port nobody listens on yet (the OS's pick, not a fixed one)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = dict(server.env("late", "vision", args={"count": 3}), CAST_ENDPOINT=f"127.0.0.1:{port}")
    proc = subprocess.Popen([sys.executable, "-m", "cast.run", "itest_components:Writer"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    time.sleep(1.0)  # the component's first calls find nobody
    late = serve(server.config_path, listen=f"127.0.0.1:{port}", cwd=tmp_path)
    try:
        out = finish(proc)
        assert "not answering yet" in out, out
    finally:
        proc.kill()
        late.stop()


def test_a_component_launched_with_cast_token_file_alone_runs_and_a_bad_file_stops_it(
    server: ServerHandle, tmp_path: Path
) -> None:
    # The launch contract of `cast export --to kubernetes`: CAST_TOKEN_FILE, no CAST_TOKEN (the C++ and Java
    # runners: tests/interop/test_cpp_session.py, test_java_runner.py).
    from cast.client.runner import LaunchContract

    token = tmp_path / "filed.token"
    env = server.env("filed", "vision", args={"count": 3}, token_file=token)  # read trimmed
    runner = [sys.executable, "-m", "cast.run", "itest_components:Writer"]
    finish(subprocess.Popen(runner, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    reader = server.connect("reader", "vision")
    try:
        written = sorted(e.value.value for e in reader.get_all(Counter) if e.value.writer == "filed")
        assert written == [1001, 1002], written  # three adds, overwrites, the first deleted
    finally:
        reader._cast_close()
    # The file wins over CAST_TOKEN (it is the renewed one), as for cast.connect.
    assert LaunchContract.from_env({**env, "CAST_TOKEN": "stale.token"}).token == token.read_text().strip()
    token.write_text(" \n")
    failed = subprocess.run(runner, env=env, capture_output=True, text=True, timeout=60)
    assert failed.returncode == 2, failed.stderr
    assert failed.stderr.strip() == (
        f"cast.run: CAST_TOKEN_FILE names {token}, which is empty: point it at a token file (`cast run` renews one "
        "per component), or unset it")
    with pytest.raises(cast.InvalidArgumentError, match=f"names {tmp_path}/none, which cannot be read: point it at"):
        LaunchContract.from_env({**env, "CAST_TOKEN_FILE": str(tmp_path / "none")})
    with pytest.raises(cast.InvalidArgumentError,
                       match="missing launch environment: CAST_ENDPOINT, CAST_TOKEN or CAST_TOKEN_FILE; start"):
        LaunchContract.from_env({k: v for k, v in env.items() if k not in ("CAST_ENDPOINT", "CAST_TOKEN_FILE")})
