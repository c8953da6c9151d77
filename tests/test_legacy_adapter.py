"""The aircraft side of the legacy protocol, datagram by datagram (no flight needed).

Each test hands encoded datagrams to the adapter as its receive thread would, runs the manager's
tick hook that applies commands, and reads the acknowledgements the adapter queued for sending.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from companion.core.clock import Clock
from companion.core.params import ParamRegistry
from companion.watchdog import RuntimeContext, ThreadManager
from legacy_protocol import codec, messages
from legacy_protocol.adapter import WAIT_CAP_S, LegacyAdapter, bounded_wait_s

SENDER = ("127.0.0.1", 40000)


@pytest.fixture()
def adapter() -> Iterator[LegacyAdapter]:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry(), vehicle_id=3)
    a = LegacyAdapter(ctx, ThreadManager(ctx, []), dest="127.0.0.1:9", listen=False)
    try:
        yield a
    finally:
        a.sock.close()


def _send(a: LegacyAdapter, cmd: messages.Payload, *, vehicle_id: int = 3, seq: int = 1) -> None:
    a.handle_datagram(codec.encode(cmd, vehicle_id=vehicle_id, seq=seq, t_ns=0), SENDER)


def _acks(a: LegacyAdapter) -> list[tuple[int, int]]:
    out = []
    while (item := a.acks.get_nowait()) is not None:
        ack, addr = item
        assert addr == SENDER
        out.append((ack.command_seq, ack.result))
    return out


def test_execution_time_zero_means_unlimited_and_is_accepted(adapter: LegacyAdapter) -> None:
    params = adapter.ctx.params
    params.set("MGR_EXEC_TIME_S", 60)
    _send(adapter, messages.SetManagerParams(0, messages.UNCHANGED, messages.UNCHANGED), seq=7)
    adapter.process_commands()
    assert _acks(adapter) == [(7, messages.AckResult.ACCEPTED)]
    assert params.get("MGR_EXEC_TIME_S") == 0


def test_a_zero_period_is_still_refused(adapter: LegacyAdapter) -> None:
    before = adapter.ctx.params.get("MGR_STATUS_MS")
    _send(adapter, messages.SetManagerParams(messages.UNCHANGED, 0, messages.UNCHANGED), seq=8)
    adapter.process_commands()
    assert _acks(adapter) == [(8, messages.AckResult.BAD_VALUE)]
    assert adapter.ctx.params.get("MGR_STATUS_MS") == before


def test_a_command_for_another_aircraft_is_neither_executed_nor_answered(
    adapter: LegacyAdapter,
) -> None:
    adapter.ctx.params.set("MGR_EXEC_TIME_S", 60)
    _send(adapter, messages.SetManagerParams(0, messages.UNCHANGED, messages.UNCHANGED), vehicle_id=4)
    adapter.process_commands()
    assert _acks(adapter) == []
    assert adapter.ctx.params.get("MGR_EXEC_TIME_S") == 60
    assert adapter.counters.other_vehicle == 1


def test_a_command_that_finds_its_queue_full_is_answered_rejected(adapter: LegacyAdapter) -> None:
    for seq in range(1, 66):  # the queue holds 64; nothing consumes it in between
        _send(adapter, messages.SetManagerParams(messages.UNCHANGED, 1000, messages.UNCHANGED), seq=seq)
    assert _acks(adapter) == [(65, messages.AckResult.BAD_VALUE)]
    assert adapter.counters.queue_full == 1
    adapter.process_commands()
    acks = _acks(adapter)
    assert len(acks) == 64 and all(r == messages.AckResult.ACCEPTED for _, r in acks)


def test_the_sender_sleeps_until_its_next_message_within_a_quarter_watchdog(
        adapter: LegacyAdapter) -> None:
    """No 100 Hz poll: the sender sleeps until a message is due (or an ack is queued), and never
    longer than a quarter of its watchdog period in host time, whatever the clock's scale."""
    wait_ns = adapter.send_due()  # everything is due at the first call
    assert adapter.counters.sent == 2  # a THREAD_STATUS (of its own threads), MANAGER_STATUS
    period_ns = min(int(adapter.ctx.params.get(name)) for name in
                    ("MGR_STATUS_MS", "MGR_MSTAT_MS")) * 1_000_000
    assert period_ns - 50_000_000 < wait_ns <= period_ns
    assert adapter.send_due() > 0 and adapter.counters.sent == 2  # nothing new is due
    assert bounded_wait_s(adapter.ctx, 1000, wait_ns / 1e9) == pytest.approx(0.25)
    fast = RuntimeContext(clock=Clock(scale=20.0), params=ParamRegistry(), vehicle_id=3)
    assert bounded_wait_s(fast, 2000) == pytest.approx(0.025)  # a 100 ms window at 20x
    assert bounded_wait_s(fast, 2000, 0.2) == pytest.approx(0.01)  # due sooner: sooner
    assert bounded_wait_s(adapter.ctx, 600_000) == WAIT_CAP_S
