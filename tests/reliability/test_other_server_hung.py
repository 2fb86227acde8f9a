"""A server that hangs holds up only the calls that go to it, never writes to the other servers.

A system of two servers (``vision`` on one, ``motor`` on the other); a component bound while both
answer; then the ``motor`` server is stopped with SIGSTOP (its sockets stay open: a hung server).
The component's first write of a type it never wrote before, into ``vision``, tells that type to the
server that will hold the value and to no other, so it is acknowledged at once; a write into
``motor`` ends by its deadline.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest
from google.protobuf.wrappers_pb2 import DoubleValue, StringValue

from cast import DeadlineExceededError, UnmanagedComponent
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity
from tests.reliability.conftest import serve, write_config

CONFIG = {"system": "two", "subarchitectures": {"vision": {}, "motor": {}},
          "servers": {"main": {"subarchitectures": ["vision"]}, "motion": {"subarchitectures": ["motor"]}}}
TIMEOUT_S = 2.0  # the component's call timeout
MARGIN_S = 1.5  # what a loaded 2-core machine may add before a call returns


def test_a_new_type_written_to_one_server_is_not_held_up_by_another_that_hangs(tmp_path: Path) -> None:
    config = write_config(tmp_path / "system.yaml", CONFIG)
    motion = serve(config, extra=("--server", "motion"))
    main = serve(config, extra=("--server", "main", "--route", f"motor={motion.endpoint}"))
    component = UnmanagedComponent()
    try:
        component._cast_bind(GrpcTransport(main.endpoint, main.token("writer", "vision", privileged=True),
                                           Identity("writer", "vision", privileged=True), call_timeout=TIMEOUT_S))
        component.add("ready", StringValue(value="both servers answer"))
        os.kill(motion.process.pid, signal.SIGSTOP)
        try:
            started = time.monotonic()
            component.add("pose", DoubleValue(value=1.5))  # a type this component never wrote
            took = time.monotonic() - started
            assert component.get("pose", DoubleValue).value == 1.5
            assert took < TIMEOUT_S, f"the write into vision took {took:.1f} s: it waited for the hung server"
            started = time.monotonic()
            with pytest.raises(DeadlineExceededError):
                component.add("pose", DoubleValue(value=2.5), subarchitecture="motor")
            took = time.monotonic() - started
            assert took < TIMEOUT_S + MARGIN_S, f"the write into motor ended after {took:.1f} s"
        finally:
            os.kill(motion.process.pid, signal.SIGCONT)
    finally:
        component._cast_close()
        main.stop()
        motion.stop()
