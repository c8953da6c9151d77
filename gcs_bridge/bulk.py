"""Paced bulk transfers on one link: log downloads, FTP replies and bursts, log lists.

A log download or an FTP burst read is thousands of messages. Sent at once they would fill the
link's socket buffer or radio and delay the telemetry queued behind them, and LOG_DATA has no
target, so a router copies it to every ground station. Each transfer is therefore a lazy
iterator of messages, drained by the link's sender a little at a time: at most a byte budget
per second (a token bucket) and at most `STEP_BUDGET_NS` of work per sender cycle, after the
telemetry that is due. A transfer may yield None for work done without a message (a CRC over
a large file), so long work is cut into pieces too.

The budget is charged with the bytes each message really took on the wire once packed
(signature included, MAVLink 2's trimmed zeros excluded), so a signed link stays within it too;
`message_bytes` is only the estimate for a message the sender did not pack. A ground station
can ask faster than any budget drains, so every channel holds at most `MAX_PENDING` transfers:
beyond that the oldest one not under way is dropped (`BulkStats.dropped`), and the memory a
request flood can take is bounded whatever its rate.

Runs in the link's send thread only; the receive thread hands transfers over by posting a
callable to the link's queue.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from gcs_bridge.dialect import Message as Msg

log = logging.getLogger(__name__)

STEP_BUDGET_NS = 2_000_000  # longest bulk work per sender cycle
BURST_S = 0.05  # the token bucket holds this many seconds of budget
FRAME_OVERHEAD_BYTES = 12
MAX_PENDING = 16  # transfers waiting per channel: a request flood's memory is bounded by this
IDLE_NS = 1 << 62

Transfer = Iterator[Msg | None]
Alive = Callable[[], bool]


@dataclass
class _Channel:
    pending: deque[tuple[Transfer, Alive | None]] = field(default_factory=deque)
    started: bool = False  # the head has produced something


@dataclass
class BulkStats:
    sent: int = 0
    bytes: int = 0
    abandoned: int = 0  # under way, then stopped: client silent, superseded or cancelled
    failed: int = 0
    dropped: int = 0  # never started: pushed out of a full channel by newer requests


def message_bytes(msg: Msg) -> int:
    """Bytes a message takes on the wire (upper bound: MAVLink 2 trims trailing zeros)."""
    unpacker = getattr(msg, "unpacker", None)
    payload = int(unpacker.size) if unpacker is not None else 255
    return payload + FRAME_OVERHEAD_BYTES


def wire_bytes(msg: Msg) -> int:
    """Bytes `msg` took when it was last packed (pymavlink keeps the frame), else the estimate:
    the real frame counts a signature the estimate does not know of."""
    try:
        packed = len(msg.get_msgbuf())
    except Exception:  # not a pymavlink message, or one never packed
        packed = 0
    return packed if packed > 0 else message_bytes(msg)


class BulkSender:
    """Named channels of transfers, drained fairly and within a byte rate.

    `replace` starts a transfer that supersedes whatever the channel was doing (a new log
    data request); `queue` appends one after the channel's others (FTP requests), except
    that a transfer already under way is abandoned when a new request comes: a client only
    asks again once it has given up on the answer it was getting. A channel holds at most
    `max_pending` transfers (the oldest waiting one goes first: its client has asked again or
    moved on since), so nothing a client sends grows the sender without bound.
    """

    def __init__(self, bytes_per_s: Callable[[], float], *,
                 max_pending: int = MAX_PENDING) -> None:
        if max_pending < 1:
            raise ValueError(f"max_pending must be at least 1, not {max_pending}")
        self._bytes_per_s = bytes_per_s
        self._max_pending = max_pending
        self._channels: dict[str, _Channel] = {}
        self._tokens = 0.0
        self._last_ns = 0
        self._order: list[str] = []
        self.stats = BulkStats()

    def replace(self, channel: str, transfer: Transfer, alive: Alive | None = None) -> None:
        """Start `transfer` instead of whatever `channel` was doing. `alive` says whether the
        client that asked is still there; a transfer whose client vanished is abandoned."""
        self.cancel(channel)
        self._channel(channel).pending.append((transfer, alive))

    def queue(self, channel: str, transfer: Transfer, alive: Alive | None = None, *,
              preempt: bool = True) -> None:
        """Append `transfer`; with `preempt`, a transfer already under way is dropped first."""
        ch = self._channel(channel)
        if preempt and ch.started and ch.pending:
            self._drop_head(ch)
        ch.pending.append((transfer, alive))
        while len(ch.pending) > self._max_pending:
            # the oldest transfer not under way: the head keeps going unless it never started
            index = 1 if ch.started else 0
            dropped, _alive = ch.pending[index]
            del ch.pending[index]
            self.stats.dropped += 1
            _close(dropped)

    def cancel(self, channel: str) -> None:
        ch = self._channels.get(channel)
        while ch is not None and ch.pending:
            self._drop_head(ch)

    def _drop_head(self, ch: _Channel) -> None:
        transfer, _alive = ch.pending.popleft()
        if ch.started:
            self.stats.abandoned += 1
        ch.started = False
        _close(transfer)

    def busy(self) -> bool:
        return any(ch.pending for ch in self._channels.values())

    def pending(self, channel: str | None = None) -> int:
        """Transfers waiting or under way on `channel` (on every channel with None)."""
        if channel is not None:
            ch = self._channels.get(channel)
            return len(ch.pending) if ch is not None else 0
        return sum(len(ch.pending) for ch in self._channels.values())

    def _channel(self, name: str) -> _Channel:
        ch = self._channels.get(name)
        if ch is None:
            ch = self._channels[name] = _Channel()
            self._order.append(name)
        return ch

    def step(self, now_ns: int, emit: Callable[[list[Msg]], None]) -> int:
        """Send what the budget allows; returns ns until more can be sent (huge when idle)."""
        rate = max(1.0, float(self._bytes_per_s()))
        if self._last_ns:
            self._tokens = min(rate * BURST_S,
                               self._tokens + rate * max(0, now_ns - self._last_ns) / 1e9)
        else:
            self._tokens = rate * BURST_S
        self._last_ns = now_ns
        if not self.busy():
            return IDLE_NS
        t_end = time.perf_counter_ns() + STEP_BUDGET_NS
        progressed = True
        while progressed and self._tokens > 0 and time.perf_counter_ns() < t_end:
            progressed = False
            for name in list(self._order):  # one message per channel per round: fair
                ch = self._channels[name]
                if not ch.pending:
                    continue
                transfer, alive = ch.pending[0]
                if alive is not None and not alive():
                    log.info("bulk transfer on channel %s abandoned: its client went silent",
                             name)
                    self._drop_head(ch)
                    progressed = True
                    continue
                try:
                    item = next(transfer)
                except StopIteration:
                    ch.pending.popleft()
                    ch.started = False
                    progressed = True
                    continue
                except Exception:  # a transfer's bug ends that transfer, not the link
                    log.exception("bulk transfer on channel %s failed", name)
                    self.stats.failed += 1
                    self._drop_head(ch)
                    continue
                ch.started = True
                progressed = True
                if item is None:
                    continue
                emit([item])
                size = wire_bytes(item)  # after packing: what the link really carried
                self._tokens -= size
                self.stats.sent += 1
                self.stats.bytes += size
        if not self.busy():
            return IDLE_NS
        if self._tokens > 0:
            return 0  # stopped by the time budget: go on after the next telemetry check
        return max(0, int(-self._tokens / rate * 1e9))


def _close(transfer: Transfer) -> None:
    close = getattr(transfer, "close", None)
    if close is not None:
        try:
            close()
        except Exception:  # a generator's cleanup failing must not stop the sender
            log.exception("closing a bulk transfer")
