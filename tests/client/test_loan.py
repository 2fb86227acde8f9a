"""Loans: a large value's bytes written in place (docs/client-protocol.md, "Writing a large value in place").

A real server on port 0 in a thread of this process (tests.client.shm_host),
components over gRPC; the in-process transport for the fallback it has.
"""

from __future__ import annotations

from typing import Any

import numpy
import pytest
from cast_testing_pb2 import Frame, Pose
from google.protobuf.wrappers_pb2 import BytesValue

import cast
from cast.client import shm
from cast.client.local_transport import LocalTransport
from cast.core.records import Identity, Limits
from tests.client.shm_host import MIB
from tests.client.shm_host import host as host  # the fixture, used by name
from tests.conftest import wait_for

FRAME = "cast.testing.Frame"


def pixels(size: int, seed: int = 0) -> bytes:
    return bytes((seed + i) % 251 for i in range(256)) * (size // 256)


def session_of(component: Any) -> Any:
    """The component's shared-memory session with its server."""
    return component._transport._directory.shared.session()


def test_a_loan_is_filled_in_place_and_readers_get_the_frame_by_shared_memory(host: Any) -> None:
    h = host()
    writer, reader = h.component("writer"), h.component("reader")
    seen: list[tuple[Frame, bool]] = []
    reader.on_change(cast.address_filter("camera", include_entry=True),
                     lambda ch: seen.append((ch.entry(Frame).value, ch.view().shared)))
    data = pixels(MIB, 3)
    with writer.loan(Frame(width=512, height=512, encoding="mono32"), "pixels", MIB) as loan:
        assert loan.shared and loan.size == MIB and len(loan.buffer) == MIB and not loan.buffer.readonly
        assert numpy.frombuffer(loan.buffer, dtype=numpy.uint8).ctypes.data % 64 == 0  # on a cache line
        loan.buffer[:] = data
        result = writer.add("camera", loan)
    expected = Frame(width=512, height=512, encoding="mono32", pixels=data)
    assert writer.get("camera", Frame) == expected
    wait_for(lambda: seen, what="the event")
    assert seen == [(expected, True)]
    with reader.get_view("camera") as view:
        assert view.shared and view.version == result.version and bytes(view.field(4)) == data
    assert h.shared()["staged_writes"] == 1


def test_a_loaned_write_names_its_region_and_copies_nothing(host: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    h = host()
    writer = h.component("writer")
    writer.add("camera", Frame(width=1))
    session = session_of(writer)

    def no_copy(data: Any) -> None:
        raise AssertionError("a loaned value was copied into the staging area")

    monkeypatch.setattr(session, "stage", no_copy)
    loan = writer.loan(Frame(width=2, height=3), "pixels", 2 * MIB)
    staged = loan._staged
    loan.buffer[:] = pixels(2 * MIB, 5)
    # The buffer is the staging area itself: what the write will name is there already.
    header = Frame(width=2, height=3).SerializeToString()
    placed = bytes(session._staging_view[staged.offset: staged.offset + staged.size])
    assert placed[:len(header)] == header and placed[-2 * MIB:] == pixels(2 * MIB, 5)
    writer.overwrite("camera", loan)
    assert writer.get("camera", Frame) == Frame(width=2, height=3, pixels=pixels(2 * MIB, 5))
    assert h.shared()["staged_writes"] == 1
    with pytest.raises(ValueError, match="written or closed"):
        loan.buffer  # noqa: B018 - the property is what is tested


def test_an_async_overwrite_takes_a_loan_and_spends_it(host: Any) -> None:
    h = host()
    writer = h.component("writer")
    added = writer.add("camera", Frame())
    loan = writer.loan(Frame(encoding="rgb8"), "pixels", MIB)
    loan.buffer[:] = pixels(MIB, 7)
    future = writer.overwrite_async("camera", loan, expected_version=added.version)
    written = future.result(10)
    assert writer.get("camera", Frame) == Frame(encoding="rgb8", pixels=pixels(MIB, 7))
    with pytest.raises(cast.InvalidArgumentError, match="already written"):
        writer.overwrite("camera", loan)
    assert writer.get_entry("camera", Frame).version == written.version


def test_with_shared_memory_off_a_loan_is_private_memory_and_the_value_the_same(
    host: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    h = host()
    reader = h.component("reader")
    monkeypatch.setenv(shm.ENV, "off")
    remote = h.component("remote")
    with remote.loan(Frame(width=640), "pixels", MIB) as loan:
        assert not loan.shared
        loan.buffer[:] = pixels(MIB, 9)
        remote.add("camera", loan)
    assert reader.get("camera", Frame) == Frame(width=640, pixels=pixels(MIB, 9))
    with reader.get_view("camera") as view:
        assert view.shared  # the server keeps it in shared memory for its host's readers all the same


def test_a_small_loan_is_private_memory(host: Any) -> None:
    h = host()
    writer = h.component("writer")
    with writer.loan(Frame(height=4), "pixels", 100) as loan:
        assert not loan.shared
        loan.buffer[:] = b"x" * 100
        writer.add("small", loan)
    assert writer.get("small", Frame) == Frame(height=4, pixels=b"x" * 100)
    assert h.shared()["staged_writes"] == 0


def test_a_loan_over_the_in_process_transport_is_written_as_bytes(host: Any) -> None:
    h = host()
    c = cast.UnmanagedComponent()
    c._cast_bind(LocalTransport(h.system, Identity("inside", "vision")))
    h.made.append(c)
    with c.loan(BytesValue(), "value", 3) as loan:
        assert not loan.shared
        loan.buffer[:] = b"abc"
        c.add("v", loan)
    assert c.get("v", BytesValue) == BytesValue(value=b"abc")


@pytest.mark.parametrize(("value", "field", "size", "said"), [
    (Frame(), "pixel", 10, "Frame has no field 'pixel': a loan is taken of one of its top-level bytes fields "
                          r"\(pixels\)"),
    (Frame(), "encoding", 10, "field 'encoding' of cast.testing.Frame is a string: a loan is taken of a top-level "
                              "singular bytes field"),
    (Frame(), "parts", 10, "field 'parts' of cast.testing.Frame is a repeated bytes"),
    (Pose(), "tags", 10, "field 'tags' of cast.testing.Pose is a repeated string"),
    (Pose(), "x", 10, r"Pose has no field 'x'|field 'x' of cast.testing.Pose is a double"),
    (Frame(pixels=b"ab"), "pixels", 10, "field 'pixels' of cast.testing.Frame already holds 2 bytes: leave it "
                                        "empty"),
    (Frame(), "pixels", -1, "a loan's size is a number of bytes, 0 or more, not -1"),
])
def test_a_loan_of_what_cannot_be_loaned_is_refused_and_takes_nothing(
    host: Any, value: Any, field: str, size: int, said: str
) -> None:
    h = host()
    writer = h.component("writer")
    with pytest.raises(cast.InvalidArgumentError, match=said):
        writer.loan(value, field, size)
    # Nothing taken: a loan of nearly the whole staging area still fits.
    with writer.loan(Frame(), "pixels", 15 * MIB) as loan:
        assert loan.shared


def test_a_loan_is_written_once_and_to_its_own_subarchitecture(host: Any) -> None:
    h = host()
    writer = h.component("writer")
    loan = writer.loan(Frame(), "pixels", MIB)
    with pytest.raises(cast.InvalidArgumentError,
                       match="taken for subarchitecture 'vision' and is written to 'language': take it with "
                             "subarchitecture 'language'"):
        writer.add("camera", loan, subarchitecture="language")
    assert not writer.exists("camera", subarchitecture="language")
    writer.add("camera", loan)  # still usable after the refusal
    with pytest.raises(cast.InvalidArgumentError, match="this loan was already written"):
        writer.overwrite("camera", loan)
    closed = writer.loan(Frame(), "pixels", MIB)
    closed.close()
    with pytest.raises(cast.InvalidArgumentError, match="already written \\(or closed\\)"):
        writer.add("other", closed)
    assert not writer.exists("other")
    with pytest.raises(cast.InvalidArgumentError, match="a batch takes messages"):
        writer.batch([("overwrite", "camera", writer.loan(Frame(), "pixels", 10))])


def test_a_closed_loan_gives_its_place_back(host: Any) -> None:
    h = host(limits=Limits(max_value_bytes=2 * MIB))  # a staging area of 4 MiB
    writer = h.component("writer")
    first = writer.loan(Frame(), "pixels", 3 * MIB)
    assert first.shared
    held = writer.loan(Frame(), "pixels", 3 * MIB)
    assert not held.shared  # no room beside the first
    held.close()
    first.close()
    again = writer.loan(Frame(), "pixels", 3 * MIB)
    assert again.shared  # the first's place was given back
    again.close()


def test_a_loan_outlives_its_session_and_is_written_as_bytes(host: Any) -> None:
    h = host()
    writer = h.component("writer")
    loan = writer.loan(Frame(width=8), "pixels", MIB)
    assert loan.shared
    session_of(writer).close()  # ended (as by a server restart): the loan's bytes stay mapped
    loan.buffer[:] = pixels(MIB, 2)
    writer.add("camera", loan)
    assert writer.get("camera", Frame) == Frame(width=8, pixels=pixels(MIB, 2))
