"""Helpers of the live-view tests: `cast foxglove` processes and a real Foxglove WebSocket client.

The server side is the `foxglove-sdk` package inside `cast foxglove` / `cast run --foxglove`, always on port 0
(the bound port is read from the first line printed). The client side speaks the protocol with the `websockets`
package, as the Foxglove app does: serverInfo and advertise as JSON text frames, subscribe as JSON, message data
as binary frames (opcode 1, subscription id, log time, payload).
"""

from __future__ import annotations

import base64
import json
import re
import socket
import struct
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import Message
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from cast.testing import wait_for
from tests.conftest import stop_process
from tests.recording.conftest import CAST, cli_env
from tests.recording.conftest import recorders as recorders  # the fixture, for the recording comparison

SUBPROTOCOL = "foxglove.sdk.v1"  # the name foxglove-sdk's server speaks (the protocol of foxglove.websocket.v1)
COMPONENTS = Path(__file__).resolve().parent / "components"
URL = re.compile(r"listening on (ws://\S+)")
UNKNOWN_CHANNEL = re.compile(r"Unknown channel ID: (\d+)")


@dataclass
class ViewProcess:
    """A running `cast foxglove`, its output collected line by line."""

    process: subprocess.Popen[str]
    url: str
    first_line: str
    lines: list[str] = field(default_factory=list)

    def output(self) -> str:
        return "".join(self.lines)

    def stop(self, sig: int) -> int:
        """Signal it as a person would; its exit status."""
        self.process.send_signal(sig)
        try:
            return self.process.wait(60)
        finally:
            stop_process(self.process, 5)


def start_view(endpoint: str, *args: str) -> ViewProcess:
    """Start `cast foxglove --endpoint ENDPOINT --listen 127.0.0.1:0 ARGS...`; wait for its first line."""
    proc = subprocess.Popen([CAST, "foxglove", "--endpoint", endpoint, "--listen", "127.0.0.1:0", *args],
                            env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    first = proc.stdout.readline()
    found = URL.search(first)
    if found is None:
        proc.kill()
        raise AssertionError(f"cast foxglove did not start: {first}{proc.stdout.read()}")
    view = ViewProcess(proc, found.group(1), first, [first])

    def drain() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            view.lines.append(line)

    threading.Thread(target=drain, daemon=True).start()
    return view


@pytest.fixture
def views() -> Iterator[list[ViewProcess]]:
    """Views a test starts (append them); any still running at the end is stopped."""
    started: list[ViewProcess] = []
    yield started
    for v in started:
        stop_process(v.process, 5)


def port_is_free(url: str) -> bool:
    """Whether a new listener could take the port of ``url`` (as a restarted view would: SO_REUSEADDR)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", int(url.rsplit(":", 1)[1])))
            s.listen()
        except OSError:
            return False
    return True


@dataclass
class Received:
    """One message data frame: the channel it came on, its log time (ns) and its payload."""

    topic: str
    log_time: int
    data: bytes


class FoxgloveClient:
    """A Foxglove WebSocket client: what it was told (serverInfo, channels, status) and the messages it received."""

    def __init__(self, url: str) -> None:
        self._stack = ExitStack()
        self.ws: ClientConnection = self._stack.enter_context(
            connect(url, subprotocols=[Subprotocol(SUBPROTOCOL)], proxy=None, open_timeout=30))
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}  # by topic
        self.status: list[dict[str, Any]] = []
        self.messages: list[Received] = []
        self._subscriptions: dict[int, str] = {}
        self._by_topic: dict[str, list[Received]] = {}

    def close(self) -> None:
        self._stack.close()

    def _pump(self, timeout: float) -> None:
        """Take the frames that arrive within ``timeout`` seconds (at least the first one, if any)."""
        try:
            frame = self.ws.recv(timeout=timeout)
        except TimeoutError:
            return
        if isinstance(frame, str):
            self._control(json.loads(frame))
        else:
            opcode, subscription, log_time = struct.unpack_from("<BIQ", frame)
            assert opcode == 1, f"unexpected binary opcode {opcode}"
            received = Received(self._subscriptions[subscription], log_time, bytes(frame[13:]))
            self.messages.append(received)
            self._by_topic.setdefault(received.topic, []).append(received)

    def _control(self, message: dict[str, Any]) -> None:
        op = message["op"]
        if op == "serverInfo":
            self.server_info = message
        elif op == "advertise":
            for channel in message["channels"]:
                self.channels[channel["topic"]] = channel
        elif op == "unadvertise":
            gone = set(message["channelIds"])
            self.channels = {t: c for t, c in self.channels.items() if c["id"] not in gone}
        elif op == "status":
            self.status.append(message)
            unknown = UNKNOWN_CHANNEL.search(message.get("message", ""))
            if unknown:
                self._subscribe_again(int(unknown.group(1)))

    def wait(self, condition: Callable[[], Any], what: str, timeout: float = 60.0) -> Any:
        """Read frames until ``condition()`` holds; its value (cast.testing.wait_for: the timeout guards against a
        hang only, and its failure says what had come)."""
        def pumped() -> Any:
            value = condition()
            if not value:
                self._pump(0.2)
            assert value, (f"channels {self.channels}, subscriptions {self._subscriptions}, {len(self.messages)} "
                           f"messages, status {self.status}")
            return value

        return wait_for(pumped, timeout, what)

    def channel(self, topic: str) -> dict[str, Any]:
        """The advertised channel of a topic, waiting for its advertisement."""
        return dict(self.wait(lambda: self.channels.get(topic), f"channel {topic}"))

    def subscribe(self, *topics: str) -> None:
        """Subscribe to the channels of these topics (waiting for each to be advertised)."""
        subs = []
        for topic in topics:
            sub_id = len(self._subscriptions) + 1
            self._subscriptions[sub_id] = topic
            subs.append({"id": sub_id, "channelId": self.channel(topic)["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def _subscribe_again(self, channel_id: int) -> None:
        """The server did not know a channel it had just advertised (foxglove-sdk 0.30 answers a subscription that
        comes right after the advertisement so, now and then, under load): ask again, as a person would."""
        subs = [{"id": sub_id, "channelId": channel_id} for sub_id, topic in self._subscriptions.items()
                if self.channels.get(topic, {}).get("id") == channel_id]
        if subs:
            time.sleep(0.05)
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def on(self, topic: str) -> list[Received]:
        return list(self._by_topic.get(topic, ()))

    def wait_messages(self, topic: str, count: int) -> list[Received]:
        """Wait until ``count`` messages arrived on ``topic``; those messages."""
        return list(self.wait(lambda: (found := self.on(topic)) and len(found) >= count and found,
                              f"{count} messages on {topic}"))

    def message_class(self, topic: str) -> type[Message]:
        """The message class the channel's advertised schema (a base64 FileDescriptorSet) describes."""
        channel = self.channel(topic)
        files = FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        for f in files.file:
            pool.Add(f)
        return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))

    def decode(self, topic: str) -> list[Message]:
        """The messages received on a topic, decoded through the channel's own schema (no CAST code)."""
        cls = self.message_class(topic)
        return [cls.FromString(m.data) for m in self.on(topic)]


@pytest.fixture
def clients() -> Iterator[Callable[[str], FoxgloveClient]]:
    """Connect Foxglove clients (closed at the end)."""
    made: list[FoxgloveClient] = []

    def make(url: str) -> FoxgloveClient:
        client = FoxgloveClient(url)
        made.append(client)
        assert client.ws.subprotocol == SUBPROTOCOL
        client.wait(lambda: client.server_info, "serverInfo")
        return client

    yield make
    for c in made:
        c.close()
