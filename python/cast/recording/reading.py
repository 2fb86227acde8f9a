"""Reading a recording: checked on open, its channels and metadata, its changes paired with their values.

Opening fails with a clear InvalidArgumentError, before anything else happens,
for a file that is missing, not MCAP, not finished (no summary: its recorder
was killed), or not written by ``cast record``. Reads go through the summary
and chunk indexes with CRC validation on.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, DataEnd, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.summary import Summary

from cast.errors import InvalidArgumentError
from cast.recording.channels import (
    ROLE_CHANGES,
    ROLE_GAPS,
    ROLE_KEY,
    ROLE_VALUE,
    SA_KEY,
    TYPE_KEY,
    Change,
    Gap,
    parse_change,
    parse_gap,
)
from cast.recording.mcap_file import END_METADATA, HEADER_METADATA

__all__ = ["Recording", "RecordedChange"]

_MAGIC = b"\x89MCAP0\r\n"


def _shape_problem(stream: BinaryIO) -> str:
    """Why the file cannot be a finished MCAP file, judged by its first and last bytes; empty if it may be."""
    head = stream.read(len(_MAGIC))
    if head != _MAGIC:
        return "is not an MCAP file (it does not start with MCAP's magic bytes): give a file written by `cast record`"
    stream.seek(0, 2)
    if stream.tell() >= 2 * len(_MAGIC):
        stream.seek(-len(_MAGIC), 2)
        if stream.read(len(_MAGIC)) == _MAGIC:
            stream.seek(0)
            return ""
    return ("is truncated: it does not end with MCAP's magic bytes, so its recorder did not finish it (killed, or "
            "the disk filled) or the copy is incomplete; `cast record` finishes its file on Ctrl-C and SIGTERM. Its "
            "complete chunks can be read with a stream reader (mcap's StreamReader) or saved with `mcap recover`")


@dataclass(frozen=True)
class RecordedChange:
    """A change read back with its value (None for a delete, or a value the recorder did not get)."""

    change: Change
    value: bytes | None


class Recording:
    """A finished recording, open for reading; close it (or use ``with``)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._stream: BinaryIO = path.open("rb")
        except OSError as exc:
            raise InvalidArgumentError(f"cannot read the recording {path}: {exc.strerror}") from None
        problem = _shape_problem(self._stream)
        if problem:
            self._stream.close()
            raise InvalidArgumentError(f"{path} {problem}")
        try:
            self._reader = SeekingReader(self._stream, validate_crcs=True)
            summary = self._reader.get_summary()
        except (McapError, ValueError, OSError, EOFError) as exc:
            self._stream.close()
            raise InvalidArgumentError(
                f"{path} is not a readable MCAP file ({exc or type(exc).__name__}): it is damaged; give a file "
                "written by `cast record`"
            ) from None
        if summary is None:
            self._stream.close()
            raise InvalidArgumentError(
                f"{path} has no summary: its recorder did not finish it (killed, or the disk filled); `cast record` "
                "finishes its file on Ctrl-C and SIGTERM. Its complete chunks can be read by a stream reader "
                "(mcap's StreamReader) or rewritten with `mcap recover`"
            )
        self.summary: Summary = summary
        self.metadata: dict[str, dict[str, str]] = {}
        for record in self._reader.iter_metadata():
            self.metadata[record.name] = dict(record.metadata)
        if HEADER_METADATA not in self.metadata:
            self._stream.close()
            raise InvalidArgumentError(
                f"{path} is an MCAP file but not a CAST recording (it has no '{HEADER_METADATA}' metadata): give a "
                "file written by `cast record`"
            )

    # ---------------------------------------------------------------- shape

    @property
    def header(self) -> dict[str, str]:
        """What the recorder wrote when it started (system, endpoint, SAs, filters, start time)."""
        return self.metadata.get(HEADER_METADATA, {})

    @property
    def trailer(self) -> dict[str, str]:
        """What the recorder wrote when it stopped (stop time, reason, counts)."""
        return self.metadata.get(END_METADATA, {})

    def channels(self, role: str) -> list[Channel]:
        """The channels of one role (``value``, ``changes``, ``gaps``), in the order they were first used."""
        return [c for c in self.summary.channels.values() if c.metadata.get(ROLE_KEY) == role]

    def schema(self, channel: Channel) -> Schema | None:
        """The schema of a channel; None if it has none."""
        return self.summary.schemas.get(channel.schema_id) if channel.schema_id else None

    def value_channels(self) -> dict[tuple[str, str], Channel]:
        """Value channels by (SA, type)."""
        return {(c.metadata.get(SA_KEY, ""), c.metadata.get(TYPE_KEY, "")): c for c in self.channels(ROLE_VALUE)}

    @property
    def subarchitectures(self) -> list[str]:
        """The SAs the recorder watched (whether or not anything changed in them)."""
        listed = self.header.get("subarchitectures", "")
        seen = [sa for sa in listed.split(",") if sa]
        for sa, _ in self.value_channels():
            if sa not in seen:
                seen.append(sa)
        return seen

    def count(self, channel: Channel) -> int:
        """Messages on a channel."""
        stats = self.summary.statistics
        return int(stats.channel_message_counts.get(channel.id, 0)) if stats is not None else 0

    @property
    def start_ns(self) -> int:
        """Log time of the first change (ns since the epoch); 0 if there is none."""
        recorded = int(self.trailer.get("first_change_ns", "0") or 0)
        return recorded or min((t for t, _ in self._change_span()), default=0)

    @property
    def end_ns(self) -> int:
        """Log time of the last change; 0 if there is none."""
        recorded = int(self.trailer.get("last_change_ns", "0") or 0)
        return recorded or max((t for _, t in self._change_span()), default=0)

    def _change_span(self) -> list[tuple[int, int]]:
        # Without the recorder's own figures: the chunk indexes of chunks holding change records (a gap
        # marker in the same chunk may widen the span a little); no message is read.
        changes = {c.id for c in self.channels(ROLE_CHANGES)}
        out = []
        for index in self.summary.chunk_indexes:
            if changes & set(index.message_index_offsets):
                out.append((index.message_start_time, index.message_end_time))
        return out

    # -------------------------------------------------------------- content

    def changes(self, topics: Iterable[str] | None = None) -> Iterator[RecordedChange]:
        """Every change in the order recorded (revision order per SA), each with its value.

        The data section is read from start to end with a stream reader (file
        order is the order the server sent the changes in, whatever the clocks
        say; one chunk in memory at a time), with CRC validation on. ``topics``
        limits the value channels kept (change records are always read); a
        change whose value channel is left out comes with value None.
        """
        keep = None if topics is None else set(topics)
        channels = self.summary.channels
        values: dict[int, bytes] = {}
        try:
            with self.path.open("rb") as stream:
                for record in StreamReader(stream, validate_crcs=True).records:
                    if isinstance(record, DataEnd):
                        return
                    if not isinstance(record, Message):
                        continue
                    channel = channels.get(record.channel_id)
                    role = channel.metadata.get(ROLE_KEY) if channel is not None else None
                    if role == ROLE_VALUE and channel is not None and (keep is None or channel.topic in keep):
                        values[record.sequence] = record.data
                    elif role == ROLE_CHANGES:
                        change = parse_change(record.data, record.sequence)
                        value = values.pop(record.sequence, None) if change.has_value else None
                        yield RecordedChange(change, value)
        except (McapError, DecodeError, ValueError, OSError) as exc:
            raise InvalidArgumentError(f"{self.path} is damaged: {exc}") from None

    def gaps(self) -> list[Gap]:
        """The gaps the recorder marked, in order."""
        topics = [c.topic for c in self.channels(ROLE_GAPS)]
        if not topics:
            return []
        try:
            return [parse_gap(m.data, m.log_time) for _s, _c, m in self._reader.iter_messages(topics=topics)]
        except (McapError, DecodeError, ValueError) as exc:
            raise InvalidArgumentError(f"{self.path} is damaged: {exc}") from None

    def close(self) -> None:
        """Close the file."""
        self._stream.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
