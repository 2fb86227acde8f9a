"""`cast run --foxglove=127.0.0.1:0`: the same live view inside the orchestrator: where it listens is printed, a
Foxglove client sees every SA's channels, a `cast.connect` script's writes and a launched component's task decisions
decoded live, and the view ends with the run."""

from __future__ import annotations

import re
import signal
from collections.abc import Callable
from pathlib import Path

from google.protobuf.wrappers_pb2 import StringValue

import cast
from tests.conftest import wait_for
from tests.foxglove.conftest import COMPONENTS, FoxgloveClient, port_is_free
from tests.foxglove.test_cast_foxglove import CHANGES, enum_name, subscribed
from tests.orchestrator.conftest import start_cast_run

CONFIG = f"""
system: fox
python_path: [{COMPONENTS}]
subarchitectures:
  vision: {{}}
  motor:
    task_manager: {{policy: fifo, max_concurrent: 1}}
    components:
      proposer: {{language: python, kind: managed, class: fox_components:Proposer}}
"""


def test_cast_run_serves_the_live_view(tmp_path: Path, clients: Callable[[str], FoxgloveClient]) -> None:
    config = tmp_path / "system.yaml"
    config.write_text(CONFIG)
    run = start_cast_run(tmp_path, config, "--foxglove=127.0.0.1:0")
    try:
        line = wait_for(lambda: re.search(r"cast: foxglove: listening on (ws://127\.0\.0\.1:\d+) \(loopback only",
                                          run.output()), what="the view's address")
        url = line.group(1)
        assert not url.endswith(":0")
        client = clients(url)
        for topic in (CHANGES, "/cast/gaps", "/vision/cast.v1.Task", "/motor/cast.v1.Task"):
            assert client.channel(topic)["encoding"] == "protobuf"
        client.subscribe("/motor/cast.v1.Task", CHANGES)
        with cast.connect(runtime_dir=run.runtime_dir, subarchitecture="motor") as script:
            # Each question makes the proposer propose a task, which the fifo task manager adopts.
            subscribed(client, lambda i: script.add(f"q{i}", StringValue(value="why?")))
            script.add("last", StringValue(value="and?"))
            tasks = client.wait(lambda: [t for t in client.decode("/motor/cast.v1.Task") if t.name == "answer-last"
                                         and enum_name(t, "state") == "TASK_STATE_COMPLETED"], "the last answer")
        assert tasks[0].component == "proposer" and tasks[0].reason == "answered"
        names = {(c.address.subarchitecture, c.address.id) for c in client.decode(CHANGES)}
        assert ("motor", "last") in names
        assert run.stop(signal.SIGTERM) == 0, run.output()
    finally:
        if run.process.poll() is None:
            run.stop(signal.SIGKILL)
    wait_for(lambda: port_is_free(url), what="the port to be free")  # the view ended with the run
