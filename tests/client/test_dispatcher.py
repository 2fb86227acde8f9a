"""The component's dispatcher: order, its bound, blocking submitters, drain and the on_space signal."""

from __future__ import annotations

import threading

from cast.client.dispatcher import Dispatcher


def test_calls_run_in_order_on_the_dispatcher_thread_and_drain_waits_for_them() -> None:
    d = Dispatcher("t")
    ran: list[tuple[int, threading.Thread]] = []
    gate = threading.Event()
    d.submit(gate.wait, 10)
    for i in range(100):
        d.submit(lambda i=i: ran.append((i, threading.current_thread())))
    assert not d.drain(0.05)  # the first call still waits at the gate
    gate.set()
    assert d.drain(10)
    assert [i for i, _ in ran] == list(range(100))
    assert {t for _, t in ran} == {d.thread}
    d.stop()


def test_a_full_queue_blocks_submitters_until_room_and_signals_space_at_half() -> None:
    d = Dispatcher("t", capacity=4)
    spaces: list[int] = []
    d.on_space = lambda: spaces.append(1)
    gate = threading.Event()
    for _ in range(4):
        d.submit(gate.wait, 10)
    assert d.room() == 0  # full: and flagged, so on_space follows once it drains
    submitted = threading.Event()

    def blocked_submitter() -> None:
        d.submit(lambda: None)  # blocks: the queue is full
        submitted.set()

    threading.Thread(target=blocked_submitter, daemon=True).start()
    assert not submitted.wait(0.1)
    d.submit(lambda: None, block=False)  # a non-blocking submit goes over the bound instead
    gate.set()
    assert submitted.wait(10)  # woken when room appeared
    assert d.drain(10)
    # Once, when the queue was back to half: on the dispatcher thread, before the later calls ran.
    assert spaces == [1]
    assert d.room() == 4
    d.stop()
