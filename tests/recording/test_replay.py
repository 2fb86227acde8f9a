"""`cast replay`: a recording written into a fresh system reproduces its entries (all of it, --sa-map, --type,
--from/--to, --rate max, --loop); a component watching the SA sees the replayed changes as it would on the robot;
conflicts with live writers are reported; bad input changes nothing."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
from pathlib import Path
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Pose
from google.protobuf import descriptor_pb2

import cast
from cast.client.filters import ChangeFilter
from cast.v1 import directory_pb2, directory_pb2_grpc
from tests.conftest import ServerHandle, stop_process, wait_for
from tests.recording.conftest import CAST, Scenario, cli_env, component_env, entries
from tests.recording.conftest import cast as cast_cli


def replay(server: ServerHandle, scenario: Scenario, *args: str) -> subprocess.CompletedProcess[str]:
    return cast_cli("replay", str(scenario.path), "--endpoint", server.endpoint, *args)


def test_a_replay_into_a_fresh_system_reproduces_the_recorded_entries(server: ServerHandle, scenario: Scenario) -> None:
    out = replay(server, scenario, "--rate", "max")
    assert out.returncode == 0, out.stderr
    assert {sa: entries(server, sa) for sa in ("vision", "language")} == scenario.final
    assert "6 changes written (4 add, 1 overwrite, 1 delete) in 1 pass(es); 0 conflict(s)" in out.stderr
    # Task decisions are in the recording but belong to the live task managers: counted, not written.
    assert "not written: " in out.stderr and "task changes" in out.stderr
    listed = json.loads(cast_cli("ls", "--endpoint", server.endpoint, "--json").stdout)
    assert {e["author"] for e in listed} == {"cast-replay"} and "cast.v1.Task" not in {e["type"] for e in listed}


def test_sa_map_and_type_choose_where_and_what(server_factory: Any, scenario: Scenario) -> None:
    # No motor here: the recording has only task changes there, which are not replayed, so it needs no target.
    live = server_factory({"system": "other", "subarchitectures": {"camera": {}, "language": {}}})
    out = replay(live, scenario, "--rate", "max", "--sa-map", "vision=camera")
    assert out.returncode == 0, out.stderr
    assert entries(live, "camera") == scenario.final["vision"]
    assert entries(live, "language") == scenario.final["language"]
    assert "into vision->camera, language" in out.stderr
    only = server_factory({"system": "poses", "subarchitectures": {"camera": {}, "language": {}}})
    out = replay(only, scenario, "--rate", "max", "--sa-map", "vision=camera", "--type", "cast.testing.Pose")
    assert out.returncode == 0, out.stderr
    assert entries(only, "camera") == {"p1": scenario.final["vision"]["p1"]}  # not the Counter c1
    assert entries(only, "language") == scenario.final["language"]


def test_from_and_to_pick_a_window_of_the_recording(server: ServerHandle, scenario: Scenario) -> None:
    # Phase B only (about 1 s after the start): the overwrite of p1 (which this replay never added: it adds it),
    # the add of c1, and the delete of p2 (not in the live system: nothing to do).
    out = replay(server, scenario, "--rate", "max", "--from", "0.5", "--to", "1.5")
    assert out.returncode == 0, out.stderr
    assert entries(server, "vision") == scenario.final["vision"] and entries(server, "language") == {}
    assert "3 changes written" not in out.stderr and "2 changes written (1 add, 1 overwrite, 0 delete)" in out.stderr
    assert "not written: 1 deletes of entries the live system does not have" in out.stderr


def test_a_component_watching_the_sa_receives_the_replayed_changes(server: ServerHandle, scenario: Scenario) -> None:
    watcher = subprocess.Popen([str(Path(CAST).parent / "python"), "-m", "cast.run", "rec_components:Watcher"],
                               env=component_env(server, "dev", "vision"), stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(watcher.stdout or []), daemon=True).start()
    try:
        wait_for(lambda: "WATCHING\n" in lines, what="the component to start")
        out = replay(server, scenario)  # at the recorded pace (--rate 1.0)
        assert out.returncode == 0, out.stderr
        wait_for(lambda: len(lines) >= 6, what="the replayed changes")
    finally:
        stop_process(watcher, 10)
    seen = [json.loads(line) for line in lines if line.startswith("{")]
    assert [(s["op"], s["id"], s.get("value")) for s in seen] == [
        ("ADD", "p1", 'x: 1 label: "p1"'),
        ("ADD", "p2", 'x: 2 label: "p2"'),
        ("OVERWRITE", "p1", 'x: 1.5 label: "p1b"'),
        ("ADD", "c1", 'writer: "w" value: 1'),
        ("DELETE", "p2", None),
    ]
    assert {s["by"] for s in seen} == {"cast-replay"}


class Meddler(cast.UnmanagedComponent):
    """A live writer that changes p1 as soon as the replay adds it."""

    def start(self) -> None:
        self.on_change(ChangeFilter(subarchitecture="vision", id="p1", operations=frozenset({cast.Operation.ADD})),
                       lambda change: self.overwrite("p1", Pose(label="mine")))


def test_conflicts_with_live_writers_are_reported_and_the_live_state_stands(
    server: ServerHandle, scenario: Scenario
) -> None:
    live = server.connect("live", "language")
    meddler = server.connect("meddler", "vision", cls=Meddler)
    try:
        meddler.start()
        live.add("q1", Pose(label="live"))  # the id the recording adds in phase C is taken
        out = replay(server, scenario)  # at the recorded pace: the meddler changes p1 before its recorded overwrite
        assert out.returncode == 1, out.stderr  # 1: something was not as recorded
        stderr = " ".join(out.stderr.split())
        assert "conflict: OVERWRITE vision/p1 (recorded revision 3 by w)" in stderr
        assert "is at version" in stderr and "the live state stands" in stderr
        assert "conflict: ADD language/q1 (recorded revision 1 by w): the id is taken in the live system" in stderr
        assert "2 conflict(s)" in stderr
        assert entries(server, "vision")["p1"] == ("cast.testing.Pose", 'label: "mine"')
        assert entries(server, "language") == {"q1": ("cast.testing.Pose", 'label: "live"')}
    finally:
        live._cast_close()
        meddler._cast_close()


def test_loop_replays_until_interrupted_each_pass_from_the_same_start(server: ServerHandle, scenario: Scenario) -> None:
    counter = server.connect("counter", "vision")
    adds: list[str] = []
    counter.on_change(ChangeFilter(subarchitecture="vision", id="p1", operations=frozenset({cast.Operation.ADD})),
                      lambda change: adds.append(change.id))
    proc = subprocess.Popen([CAST, "replay", str(scenario.path), "--endpoint", server.endpoint, "--loop", "--rate",
                             "max", "--sa-map", "language=motor"], env=cli_env(), stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: len(adds) >= 3, what="three passes")
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        stop_process(proc, 5)
        counter._cast_close()
    assert proc.returncode == 0, stderr
    assert "stopped by SIGINT" in stderr and "in 1 pass(es)" not in stderr
    # Each pass deleted what the last one left, so no pass met its own entries as conflicts.
    assert "0 conflict(s)" in stderr


@pytest.mark.timeout(300)  # a dozen `cast replay` processes: a minute on a busy machine
def test_bad_input_is_refused_naming_what_is_wrong_and_changes_nothing(
    server: ServerHandle, scenario: Scenario, tmp_path: Path
) -> None:
    def refused(*args: str, path: str | None = None) -> str:
        out = cast_cli("replay", path or str(scenario.path), "--endpoint", server.endpoint, "--rate", "max", *args)
        assert out.returncode == 2, (args, out.stderr)
        return " ".join(out.stderr.split())

    foreign = tmp_path / "system.yaml"
    foreign.write_text("system: test\n")
    assert "is not an MCAP file (it does not start with MCAP's magic bytes)" in refused(path=str(foreign))
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(scenario.path.read_bytes()[:-100])
    assert "is truncated" in refused(path=str(truncated))
    assert "cannot read the recording" in refused(path=str(tmp_path / "missing.mcap"))
    assert ("--sa-map visoin=vision: the recording has no subarchitecture 'visoin' (it holds: vision, language, motor)"
            in refused("--sa-map", "visoin=vision"))
    assert ("--sa-map vision=camera: the live system has no subarchitecture 'camera' (known: vision, language, motor)"
            in refused("--sa-map", "vision=camera"))
    assert "--sa-map 'vision': write RECORDED=LIVE" in refused("--sa-map", "vision")
    assert "--rate 0.0: give a speed factor above 0" in refused("--rate", "0")
    assert "--from 3.0 --to 1.0: give 0 <= FROM < TO" in refused("--from", "3", "--to", "1")
    assert "--from 60.0: the recording lasts" in refused("--from", "60")
    assert ("--type cast.testing.Poze: the recording has no values of that type (it holds: cast.testing.Counter, "
            "cast.testing.Pose, cast.v1.Task)") in refused("--type", "cast.testing.Poze")
    # A type whose schema differs from the live server's: refused before anything is written.
    other = descriptor_pb2.FileDescriptorProto(name="cast_testing.proto", package="cast.testing", syntax="proto3")
    pose = other.message_type.add(name="Pose")
    pose.field.add(name="title", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_STRING,
                   label=descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL)
    with grpc.insecure_channel(server.endpoint) as channel:
        directory_pb2_grpc.DirectoryStub(channel).RegisterSchemas(
            directory_pb2.RegisterSchemasRequest(files=descriptor_pb2.FileDescriptorSet(file=[other])),
            metadata=(("authorization", f"Bearer {server.token('other', 'vision')}"),), timeout=10)
    answer = refused()
    assert "has another schema in the live system" in answer and "nothing was written" in answer
    unprivileged = cast_cli("replay", str(scenario.path), "--endpoint", server.endpoint, "--type", "cast.testing.Pose",
                            env=cli_env(CAST_TOKEN=server.token("dev", "vision")))
    assert unprivileged.returncode == 2 and "is not privileged" in unprivileged.stderr
    for sa in ("vision", "language", "motor"):
        assert entries(server, sa) == {}, sa
