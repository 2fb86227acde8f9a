"""Writing a recording: channel messages into an MCAP file, chunked, compressed, indexed on finish.

The file is written in place (no temporary name), and the chunk in progress is
flushed at least every :data:`FLUSH_SECONDS`: a recorder that is killed outright
leaves every complete chunk readable by a stream reader; one stopped by SIGINT
or SIGTERM calls :meth:`RecordingWriter.finish`, which writes the summary and
the indexes that seeking readers and Foxglove use.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import BinaryIO

from mcap.writer import CompressionType, Writer

from cast.recording.channels import ChannelMessage, ChannelSpec

__all__ = ["END_METADATA", "FLUSH_SECONDS", "HEADER_METADATA", "LIBRARY", "RecordingWriter"]

LIBRARY = "cast record (CAST on gRPC)"
HEADER_METADATA = "cast.recording"
END_METADATA = "cast.recording.end"
FLUSH_SECONDS = 1.0
_CHUNK_BYTES = 1024 * 1024


class RecordingWriter:
    """One MCAP file being written: channels and schemas registered on first use, each schema once."""

    def __init__(self, path: Path, header: Mapping[str, str]) -> None:
        # 'x': an existing file is never overwritten (the command checks first, with a clearer message).
        self.path = path
        self._stream: BinaryIO = path.open("xb")
        self._writer = Writer(self._stream, chunk_size=_CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=LIBRARY)
        self._writer.add_metadata(HEADER_METADATA, dict(header))
        self._channels: dict[tuple[str, str, str], int] = {}
        self._schemas: dict[tuple[str, bytes], int] = {}
        self._dirty = False
        self._flushed = time.monotonic()
        self.messages = 0
        self.data_bytes = 0
        self.finished = False

    def _channel_id(self, spec: ChannelSpec) -> int:
        found = self._channels.get(spec.key)
        if found is not None:
            return found
        schema_id = 0
        if spec.schema_data:
            schema_key = (spec.schema_name, spec.schema_data)
            schema_id = self._schemas.get(schema_key, 0)
            if not schema_id:
                schema_id = self._writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
                self._schemas[schema_key] = schema_id
        channel_id = self._writer.register_channel(spec.topic, spec.message_encoding, schema_id, spec.metadata)
        self._channels[spec.key] = channel_id
        return channel_id

    def write(self, message: ChannelMessage) -> None:
        """Add one message (its channel, and the channel's schema, are written before it the first time)."""
        channel_id = self._channel_id(message.channel)
        self._writer.add_message(channel_id, message.log_time, message.data, message.log_time, message.sequence)
        self.messages += 1
        self.data_bytes += len(message.data)
        self._dirty = True

    def flush_if_due(self) -> None:
        """Close the chunk in progress if it is older than FLUSH_SECONDS, so a killed recorder loses little."""
        now = time.monotonic()
        if self._dirty and now - self._flushed >= FLUSH_SECONDS:
            self._writer.flush()  # type: ignore[no-untyped-call]  # mcap's writer is untyped here
            self._dirty = False
            self._flushed = now

    def size(self) -> int:
        """Bytes in the file so far (without the chunk in progress)."""
        return self._stream.tell()

    def finish(self, trailer: Mapping[str, str]) -> None:
        """Write the trailer metadata, the summary and the indexes, and close the file."""
        if self.finished:
            return
        self.finished = True
        self._writer.add_metadata(END_METADATA, dict(trailer))
        self._writer.finish()  # type: ignore[no-untyped-call]
        self._stream.close()
