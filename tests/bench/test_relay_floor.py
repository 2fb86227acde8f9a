"""M8's bare relay (bench/relay_floor.py): real processes, every frame to every reader, the bytes the writer wrote."""

from __future__ import annotations

from bench import relay_floor
from bench.checksum import expected_frames


def test_every_reader_reads_every_frame_the_writer_staged_even_when_it_outruns_the_arena() -> None:
    # Back to back, 40 frames through an arena of 8 slots to readers that pause after each: the relay must wait for
    # every reader to give a slot back before it copies the next value there, or a reader would sum a later frame.
    frames, size = 40, 64 << 10
    got = relay_floor.large(frames, 0.0, size, subscribers=3, reader_delay_s=0.005)
    assert sorted(got["sent"]) == list(range(frames))
    assert len(got["watchers"]) == 3
    for reader in got["watchers"]:
        assert sorted(reader["stamps"]) == list(range(frames)), reader
        assert reader["bytes"] == frames * size
        assert reader["checksum"] == expected_frames(range(frames), size)
