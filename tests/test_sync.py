"""The shared slots and queues wake a blocked OS thread at once, though writers skip the notify
when nobody waits (the per-sample path's saving)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from companion.core.sync import MessageQueue, WaitableSlot


def _until(cond: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail("condition not reached within the timeout")
        time.sleep(0.001)


def test_slot_wakes_a_blocked_reader_at_once() -> None:
    slot: WaitableSlot[int] = WaitableSlot()
    got: list[tuple[int | None, int] | None] = []
    woke: list[float] = []

    def reader() -> None:
        got.append(slot.wait_newer(0, 30.0))
        woke.append(time.monotonic())

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    _until(lambda: len(slot._waiters) == 1)  # the reader is inside Condition.wait
    sent = time.monotonic()
    slot.write(42)
    t.join(5.0)
    assert not t.is_alive()
    assert got == [(42, 1)]
    assert woke[0] - sent < 1.0  # woken by the write, not by its 30 s timeout
    assert len(slot._waiters) == 0


def test_slot_write_without_waiters_and_timeout() -> None:
    slot: WaitableSlot[str] = WaitableSlot()
    slot.write("a")  # nobody waits: no notify needed, the value is there
    assert slot.read_versioned()[:2] == ("a", 1)
    assert slot.wait_newer(1, 0.02) is None  # nothing newer: times out
    assert len(slot._waiters) == 0  # a timed-out waiter leaves no trace
    assert slot.wait_newer(0, 0.02) == ("a", 1)


def test_queue_wakes_a_blocked_consumer_at_once() -> None:
    q: MessageQueue[int] = MessageQueue(4, drop_oldest=True)
    got: list[int | None] = []

    def consumer() -> None:
        got.append(q.get(30.0))

    t = threading.Thread(target=consumer, daemon=True)
    t.start()
    _until(lambda: len(q._waiters) == 1)
    sent = time.monotonic()
    assert q.put(7)
    t.join(5.0)
    assert not t.is_alive() and got == [7]
    assert time.monotonic() - sent < 1.0


def test_full_queue_still_wakes_and_counts_drops() -> None:
    q: MessageQueue[int] = MessageQueue(2, drop_oldest=True)
    assert q.put(1) and q.put(2)
    assert not q.put(3)  # the oldest went
    assert q.dropped == 1 and q.drain() == [2, 3]
    assert q.get(0.01) is None
