"""A launched component in Python, C++ or Java waits for a server that answers late (the connect window).

Whoever launched the component started the system first, so a server that does not answer at once is
busy or still starting: each runner asks its first call again with backoff, for up to 20 s
(docs/client-protocol.md, "Start-up", step 2), instead of exiting 2. Here the component starts against
a port nobody listens on yet, and the server starts there about a second later. The components are the
start-barrier writers (cast_test_barrier.cc, BarrierWriter.java, barrier_components.py), run without
the barrier: first thing in run() they add ``<id>-0`` .. ``<id>-end``.
"""

from __future__ import annotations

import os
import socket
import sys
from pathlib import Path

import pytest

from tests.conftest import ServerHandle, serve, stop_process, wait_for
from tests.interop.child import ChildProcess
from tests.interop.cpp_support import cpp_executable
from tests.interop.java_support import RUNNER, java_classpath
from tests.orchestrator.conftest import COMPONENTS

WRITES = 3


def command(lang: str) -> list[str]:
    """The command line of the writer component in ``lang``."""
    if lang == "python":
        return [sys.executable, "-m", "cast.run", "barrier_components:BarrierWriter"]
    if lang == "cpp":
        return [str(cpp_executable("cast_test_barrier")), "writer"]
    return ["java", "-cp", java_classpath(), RUNNER, "cast.itest.BarrierWriter"]


@pytest.mark.parametrize("lang", ["python", "cpp", "java"])
def test_a_launched_component_waits_for_a_server_that_answers_late(
    server: ServerHandle, tmp_path: Path, lang: str
) -> None:
    with socket.socket() as probe:  # a port nobody listens on yet (the OS's pick, not a fixed one)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    component_id = f"late-{lang}"
    env = dict(server.env(component_id, "vision", args={"sa": "vision", "count": WRITES}),
               CAST_ENDPOINT=f"127.0.0.1:{port}")
    env["PYTHONPATH"] = os.pathsep.join([str(COMPONENTS), env["PYTHONPATH"]])
    writer = ChildProcess(component_id, command(lang), env, stdin=False)
    late = None
    reader = None
    try:
        # Its first calls find nobody (a JVM under load may take seconds to make them).
        wait_for(lambda: "not answering yet" in writer.output() or writer.proc.poll() is not None, 60,
                 f"{component_id}'s first try")
        assert writer.proc.poll() is None, f"the component gave up at once\n{writer.output()}"
        late = serve(server.config_path, listen=f"127.0.0.1:{port}", cwd=tmp_path)
        reader = late.connect("reader", "vision")
        wait_for(lambda: reader.exists(f"{component_id}-end"), 60, f"{component_id}'s writes")
        assert [reader.exists(f"{component_id}-{i}") for i in range(WRITES)] == [True] * WRITES
        writer.terminate()
        assert writer.wait(30) == 0, writer.output()
    finally:
        if reader is not None:
            reader._cast_close()
        writer.close()
        if late is not None:
            stop_process(late.process, 10)
