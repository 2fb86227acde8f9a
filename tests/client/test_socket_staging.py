"""STAGING on the shared-memory session's socket: the wake-up a client sends before copying a large value.

A client about to copy a value of ``wire.STAGING_HINT_BYTES`` or more into
its staging area sends STAGING first, so that the server's thread, likely
asleep, wakes while the copy runs rather than when the WRITES frame comes
(docs/client-protocol.md, "Frames"; docs/performance-m8.md, "Waking the
server ahead of a large write"). A real server on port 0 (in a thread of
this process); raw sessions opened by hand, as in
tests/client/test_socket_writes.py. The C++ client's use of it is tested in
cpp_client/tests/server/socket_writes_test.cc, the Java client's in
java_client's SharedMemoryTest.
"""

from __future__ import annotations

import os
import socket
import struct
from typing import Any

import pytest
from google.protobuf.wrappers_pb2 import BytesValue

from cast.client import shm_session
from cast.wire import shared_memory as wire
from tests.client.shm_host import MIB, image
from tests.client.test_socket_writes import add
from tests.client.test_socket_writes import host as host  # the fixtures, used by name
from tests.client.test_socket_writes import raw as raw


def test_the_server_reads_staging_and_answers_nothing(raw: Any) -> None:
    _, session = raw()
    wire.send(session.sock, wire.STAGING_FRAME * 3)
    session.write(add(1, "after", staged=session.stage(image(MIB))))
    # Nothing answered the STAGING frames: replies() fails on any frame but REPLIES, SEGMENT and RETIRE.
    (reply,) = session.replies(1)
    assert reply.WhichOneof("result") == "write", reply


def test_a_staging_frame_with_a_body_is_refused_naming_it(raw: Any) -> None:
    h, session = raw()
    wire.send(session.sock, wire.encode(wire.STAGING, b"ab"))
    refused = session.next_frame()
    assert refused.kind == wire.REFUSED and b"STAGING carries nothing, this one 2 bytes" in refused.body, refused
    with pytest.raises((EOFError, ConnectionResetError)):
        session.next_frame()
    # Nothing changed for anyone else.
    _, other = raw(h, "other")
    other.write(add(1, "through", b"t"))
    (reply,) = other.replies(1)
    assert reply.WhichOneof("result") == "write", reply


def test_the_python_client_sends_staging_before_large_values_only(host: Any) -> None:
    h = host()
    writer, reader = h.component("writer"), h.component("reader")
    session = writer._transport._directory.shared.session()
    assert session.hints  # the server's WELCOME says version 3 or later
    small = image(wire.STAGING_HINT_BYTES // 2)  # over the shared-memory threshold: staged, but no hint
    writer.add("small", small)
    assert session.hints_sent == 0
    large = image(wire.STAGING_HINT_BYTES)  # serialized, a few bytes over the hint's size
    writer.add("large", large)
    writer.overwrite("large", image(wire.STAGING_HINT_BYTES, 1))
    assert session.hints_sent == 2
    assert reader.get("small", BytesValue).value == small.value
    assert reader.get("large", BytesValue).value == image(wire.STAGING_HINT_BYTES, 1).value


@pytest.mark.parametrize("version", [1, 2, 3])
def test_a_client_sends_staging_only_to_a_server_whose_welcome_says_version_3(version: int) -> None:
    """A server of versions 1 and 2 would end the session on a frame of an unknown kind."""
    ours, theirs = socket.socketpair()
    ours.setblocking(False)  # as shm.connect leaves it
    staging = os.memfd_create("staging")
    os.ftruncate(staging, 4 * MIB)
    body = struct.pack("<H16s16sQQQ", version, b"s" * 16, b"i" * 16, 64 << 10, 16 * MIB, 4 * MIB)
    session = shm_session.ClientSession(ours, body, staging, "test", "token")
    try:
        data = BytesValue(value=b"x" * MIB).SerializeToString()
        assert session.stage(data) is not None
        theirs.setblocking(False)
        try:
            sent = theirs.recv(1024)
        except BlockingIOError:
            sent = b""
        assert sent == (wire.STAGING_FRAME if version >= wire.STAGING_VERSION else b""), sent
        assert session.hints_sent == (1 if version >= 3 else 0)
    finally:
        session.close()
        theirs.close()

