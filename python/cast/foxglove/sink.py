"""The Foxglove side of the live view: the WebSocket server (``foxglove-sdk``) and one channel per recording channel.

:class:`FoxgloveSink` is a :class:`cast.recording.recorder.MessageSink`: the
recorder's loop hands it the same :class:`ChannelMessage` objects it hands the
MCAP writer, and the sink announces each new channel to the connected Foxglove
clients (topic, ``protobuf`` encoding, the type's ``FileDescriptorSet`` as
schema, the channel's ``cast.*`` metadata) before its first message. The SDK
sends a message only to clients subscribed to its channel, and drops the
oldest data of a client that falls more than its backlog behind: a live view
may skip messages for a slow viewer, a recording never does (docs/foxglove.md).
"""

from __future__ import annotations

from collections.abc import Callable

import foxglove
from foxglove.websocket import WebSocketServer

from cast.errors import CastError, InvalidArgumentError
from cast.foxglove.address import DEFAULT_LISTEN
from cast.listen import ListenAddress, ListenError
from cast.recording.channels import ChannelMessage, ChannelSpec, changes_channel, gaps_channel

__all__ = ["FoxgloveSink"]

NoteSink = Callable[[str], None]
"""Where the sink says something a person should know (a channel it cannot announce)."""


class FoxgloveSink:
    """A Foxglove WebSocket server with one channel per :class:`ChannelSpec`, announced as it first appears.

    Binds at construction, so a taken port is reported before anything else
    starts; :attr:`port` is the bound port (the one chosen when asked for 0).
    Its own SDK context keeps its channels apart from any other Foxglove
    logging in the process.
    """

    def __init__(self, address: ListenAddress, name: str, note: NoteSink | None = None,
                 option: str = "--listen") -> None:
        self.address = address
        self._note = note or (lambda _text: None)
        self._context = foxglove.Context()
        try:
            self._server: WebSocketServer = foxglove.start_server(name=name, host=address.host, port=address.port,
                                                                  context=self._context)
        except (RuntimeError, OverflowError) as exc:
            raise _bind_error(address, option, str(exc)) from None
        self.port = self._server.port
        self._channels: dict[tuple[str, str, str], foxglove.Channel] = {}
        self.unshown: list[ChannelSpec] = []  # value channels without a schema: Foxglove cannot decode them
        self.messages = 0
        self._closed = False
        for spec in (changes_channel(), gaps_channel()):
            self.announce(spec)

    @property
    def url(self) -> str:
        """The ``ws://HOST:PORT`` to open in Foxglove, with the bound port."""
        return self.address.url("ws", self.port)

    def announce(self, spec: ChannelSpec) -> foxglove.Channel | None:
        """The SDK channel of a spec, created (and so advertised to clients) on first use; None without a schema."""
        channel = self._channels.get(spec.key)
        if channel is not None:
            return channel
        if not spec.schema_data:
            # The protocol needs a schema to decode protobuf; the change itself still shows on /cast/changes.
            if spec not in self.unshown:
                self.unshown.append(spec)
                self._note(f"no schema registered for {spec.type} in '{spec.subarchitecture}': its values are not "
                           f"shown (its changes are, on /cast/changes)")
            return None
        schema = foxglove.Schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data)
        channel = foxglove.Channel(spec.topic, schema=schema, message_encoding=spec.message_encoding,
                                   context=self._context, metadata=spec.metadata)
        self._channels[spec.key] = channel
        return channel

    @property
    def topics(self) -> list[str]:
        """The topics announced so far."""
        return [c.topic() for c in self._channels.values()]

    def write(self, message: ChannelMessage) -> None:
        """Send one message to the clients subscribed to its channel (announcing the channel if new)."""
        channel = self.announce(message.channel)
        if channel is not None:
            channel.log(message.data, log_time=message.log_time)
            self.messages += 1

    def flush_if_due(self) -> None:
        """Nothing to flush: the SDK sends as messages come."""

    def warn(self, text: str) -> None:
        """Show a warning in every connected Foxglove app (its problems list), e.g. a gap in the changes."""
        self._server.publish_status(text, foxglove.StatusLevel.Warning)

    def close(self) -> None:
        """Stop serving: clients are disconnected, the port released (the SDK's own thread closes it just after).

        Once; later calls do nothing.
        """
        if self._closed:
            return
        self._closed = True
        for channel in self._channels.values():
            channel.close()
        self._server.stop()


def _bind_error(address: ListenAddress, option: str, detail: str) -> CastError:
    where = f"{address.host}:{address.port}"
    if "in use" in detail:
        return ListenError(f"cannot listen on {where}: the address is in use (another `cast foxglove`, a Foxglove "
                           f"bridge, or another program): stop it, or give {option} {address.host}:PORT with a "
                           f"free port ({option} {address.host}:0 picks one and prints it)")
    if "out of range" in detail or "too large" in detail:
        return InvalidArgumentError(f"{option} {where}: the port must be from 0 to 65535")
    return ListenError(f"cannot listen on {where}: {detail.removeprefix('FoxgloveError: ')}: give an address of this "
                       f"machine, such as {DEFAULT_LISTEN}")
