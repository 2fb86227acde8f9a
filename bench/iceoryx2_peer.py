"""The zero-copy limit of M8: iceoryx2 (the `iceoryx2` package) publish -> subscribe, one host.

A publisher in the benchmark's process loans each sample from its own shared
memory, writes the frame in place (bench.peer_fanout.frame: a sequence number,
padding) and sends it; each subscriber is a process of its own
(``python -m bench.iceoryx2_peer sub SERVICE INDEX``), woken by an iceoryx2
event after each send, that reads every byte of the sample where it lies
(a memoryview of the publisher's shared memory, summed by bench.checksum)
before it stamps it. Backpressure ``RetryUntilDelivered`` and no overflow: a
send waits rather than drops when a subscriber's buffer is full, so every
sample is delivered, as CAST's ``queue`` delivery does. The service's name is
unique to the run and its files (``/dev/shm/iox2_*``) go with its last port.

This is no product's rival to CAST (no server, no history, no other host), but
the floor a same-host large-value path can approach: a figure in M8, not a
target. When the package cannot be imported, :func:`large` raises RuntimeError
with the reason, which the row shows.
"""

from __future__ import annotations

import ctypes
import os
import sys
import time
import uuid
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from bench.harness import PYTHON
from bench.peer_fanout import END, WARM, Receiver, Subscribers, drive, frame

__all__ = ["iceoryx2_version", "large"]

BUFFER = 8  # samples a subscriber may have waiting: a send past it waits (RetryUntilDelivered)


def iceoryx2_version() -> str:
    """The installed iceoryx2 release, or why there is none."""
    try:
        return version("iceoryx2")
    except PackageNotFoundError:
        return "not installed"


def _iox() -> Any:
    try:
        import iceoryx2  # imported where used: the row says why when it cannot be
    except ImportError as exc:
        raise RuntimeError(f"iceoryx2 not measured: the `iceoryx2` package cannot be imported ({exc}); "
                           "`make setup` installs the version requirements-dev.txt pins") from exc
    return iceoryx2


def _services(iox: Any, node: Any, name: str, subscribers: int) -> tuple[Any, Any]:
    pubsub = (node.service_builder(iox.ServiceName.new(name))
              .publish_subscribe(iox.Slice[ctypes.c_uint8])
              .max_subscribers(subscribers + 1)
              .subscriber_max_buffer_size(BUFFER)
              .enable_safe_overflow(False)
              .history_size(0)
              .open_or_create())
    event = node.service_builder(iox.ServiceName.new(name + "/sent")).event().open_or_create()
    return pubsub, event


class _Publisher:
    def __init__(self, size: int, subscribers: int) -> None:
        iox = self.iox = _iox()
        self.name = f"cast-bench/m8/{os.getpid()}/{uuid.uuid4().hex[:12]}"
        self.node = iox.NodeBuilder.new().create(iox.ServiceType.Ipc)
        pubsub, event = _services(iox, self.node, self.name, subscribers)
        self.publisher = (pubsub.publisher_builder()
                          .initial_max_slice_len(size)
                          .backpressure_strategy(iox.BackpressureStrategy.RetryUntilDelivered)
                          .create())
        self.notifier = event.notifier_builder().create()
        self.subs = Subscribers([PYTHON, "-m", "bench.iceoryx2_peer", "sub", self.name], subscribers)
        try:
            warm = frame(WARM, 16)
            self.subs.handshake(lambda: self.put(warm))
        except BaseException:
            self.subs.close()
            raise

    def put(self, payload: bytes) -> None:
        sample = self.publisher.loan_slice_uninit(len(payload))
        ctypes.memmove(sample.payload_ptr, payload, len(payload))
        sample.assume_init().send()
        self.notifier.notify()

    def close(self) -> None:
        self.subs.close()


def large(frames: int, gap_s: float, size: int, subscribers: int = 4, warm: int = 0,
          warm_size: int = 0, cold: int = 0) -> dict[str, Any]:
    """M8's run for iceoryx2: ``frames`` samples of ``size`` bytes, ``gap_s`` apart (0: back to back).

    Before them ``cold`` paced samples and ``warm`` of ``warm_size`` bytes back to back, as M8's writer
    sends (:func:`bench.peer_fanout.drive`).
    """
    pub = _Publisher(size, subscribers)
    try:
        sent = drive(pub.put, frames, gap_s, size, warm, warm_size, cold)
        pub.put(frame(END, 16))
        got = pub.subs.results()
    finally:
        pub.close()
    return {"sent": sent, "watchers": got}


def _subscriber(name: str) -> int:
    iox = _iox()
    node = iox.NodeBuilder.new().create(iox.ServiceType.Ipc)
    pubsub, event = _services(iox, node, name, 0)
    subscriber = pubsub.subscriber_builder().buffer_size(BUFFER).create()
    listener = event.listener_builder().create()
    receiver = Receiver(read_all=True)
    deadline = time.monotonic() + 300
    while not receiver.done.is_set() and time.monotonic() < deadline:
        listener.timed_wait(iox.Duration.from_millis(100))
        while (sample := subscriber.receive()) is not None:
            receiver.on_message(sample.payload().as_memory_view())  # the publisher's memory, read in place
            sample.delete()  # given back: the publisher may loan it again
    receiver.report()
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__" and sys.argv[1] == "sub":
    _subscriber(sys.argv[2])
