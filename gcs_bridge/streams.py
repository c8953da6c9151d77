"""The telemetry streams: one table row per message, and the per-link scheduler that runs it.

A stream's default rate is what a ground station expects of an autopilot on a network link
(attitude at 20 Hz for the HUD, the map at 5 Hz, GPS and health at 2 Hz), set by the `MAV_*_HZ`
parameters so a user's choice persists. The thread-status named values keep the manager's
`MGR_STATUS_MS`, and the thesis's per-thread message periods pace the legacy protocol only.
A link's own settings, MAV_CMD_SET_MESSAGE_INTERVAL and REQUEST_DATA_STREAM override a default
for that link. On a serial radio the default schedule is fitted to `MAV_RADIO_PCT` of the
line's byte rate (`fit_to_line`): the fastest streams are slowed first, so a 57600 baud radio
never queues more than it can send.

Streams fed by a data slot are sent *with* the data: once a stream is due, it goes out as soon
as its slot holds a sample newer than the last one sent, so a message leaves within about a
millisecond of the device frame that caused it instead of up to a whole period later. When no
new sample comes within one period, that slot is skipped (counted), never filled with stale
data.

The sender sleeps between messages rather than polling for samples. Each data source's period
is learnt from its slot's write stamps, and the sender sleeps (on the link's queue, so answers
still leave at once) until `MARGIN_HOST_NS` after the first sample expected once a stream falls
due, so one wake-up finds both the stream due and its sample there. Only a sample later than
predicted is waited for on its slot (at most `AWAIT_NS` at a time; a slot nobody can wait on is
polled every `POLL_NS`). A stream sent on time alone goes out at the first wake-up within
`TIME_SLACK_NS` after it falls due, so it rarely needs a wake-up of its own. Periods are in the
runtime's clock; predictions are in host time, because slots stamp their writes in host time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from companion.core.sync import WaitableSlot
from gcs_bridge import status, telemetry
from gcs_bridge.dialect import Identity, mavlink
from gcs_bridge.dialect import Message as Msg
from gcs_bridge.runtime_view import BridgeCore

FALLBACK_PERIOD_MS = 1000
MIN_INTERVAL_US = 2000  # 500 Hz: faster requests are clamped
POLL_NS = 1_000_000  # while a sample is imminent in a slot nobody can wait on
AWAIT_NS = 2_000_000  # longest wait on one waitable slot (queued answers wait at most this)
IDLE_NS = 1_000_000_000  # nothing due: the sender's own bound (its watchdog) applies
MARGIN_HOST_NS = 500_000  # host ns: the sender wakes this long after a sample is expected
TIME_SLACK_NS = 20_000_000  # a stream sent on time alone may wait this long for a wake-up
RATE_INTERVALS = 4  # writes seen before a source's period is trusted for predictions
PERIOD_REFRESH_NS = 100_000_000  # how soon a changed message period takes effect
LATENCY_RING = 2048
FRAME_OVERHEAD_BYTES = 12  # MAVLink 2 header and CRC
SIGNATURE_BYTES = 13


class LinkSide(Protocol):
    """What a stream builder may ask of the link it is sending on."""

    index: int
    counters: status.LinkCounters

    @property
    def identity(self) -> Identity: ...

    def next_thread_status(self) -> Any: ...


Builder = Callable[[BridgeCore, Any, LinkSide], list[Msg]]


@dataclass(frozen=True)
class StreamSpec:
    msg_id: int
    source: str | None  # VehicleState slot that drives it; None: sent on time alone
    default_ms: Callable[[BridgeCore], int | None]  # None or 0: off unless requested
    build: Builder
    groups: tuple[int, ...] = ()  # REQUEST_DATA_STREAM ids that include it
    frames: int = 1  # messages one send emits (for the radio's byte budget)

    @property
    def name(self) -> str:
        cls = mavlink.mavlink_map.get(self.msg_id)
        return str(cls.msgname) if cls is not None else str(self.msg_id)


def _rate_param(name: str) -> Callable[[BridgeCore], int | None]:
    """A default period from a `MAV_*_HZ` parameter (None: off)."""
    def period(core: BridgeCore) -> int | None:
        try:
            hz = float(core.ctx.params.get(name))
        except Exception:
            return FALLBACK_PERIOD_MS
        return max(1, round(1000.0 / hz)) if hz > 0 else None
    return period


def _param_period(name: str) -> Callable[[BridgeCore], int | None]:
    def period(core: BridgeCore) -> int | None:
        try:
            return int(core.ctx.params.get(name))
        except Exception:
            return FALLBACK_PERIOD_MS
    return period


def _fixed(ms: int | None) -> Callable[[BridgeCore], int | None]:
    return lambda core: ms


def _b_heartbeat(core: BridgeCore, _v: Any, link: LinkSide) -> list[Msg]:
    return [status.heartbeat(core, link.identity)]


def _b_sys_status(core: BridgeCore, _v: Any, link: LinkSide) -> list[Msg]:
    return [status.sys_status(core, link.counters)]


def _b_system_time(core: BridgeCore, _v: Any, _l: LinkSide) -> list[Msg]:
    return [status.system_time(core)]


def _b_thread_status(core: BridgeCore, _v: Any, link: LinkSide) -> list[Msg]:
    st = link.next_thread_status()
    return [] if st is None else status.thread_status_messages(core, st)


def _b_highres(core: BridgeCore, imu: Any, _l: LinkSide) -> list[Msg]:
    return telemetry.highres_imu(core, imu, core.ctx.state.imu_slow.read())


def _b_scaled(core: BridgeCore, imu: Any, _l: LinkSide) -> list[Msg]:
    return telemetry.scaled_imu(core, imu, core.ctx.state.imu_slow.read())


def _b_extended(core: BridgeCore, _v: Any, _l: LinkSide) -> list[Msg]:
    return telemetry.extended_sys_state(core, core.ctx.state.estimator.read())


def _b_vfr(core: BridgeCore, est: Any, _l: LinkSide) -> list[Msg]:
    control = core.ctx.state.control.read()
    return telemetry.vfr_hud(core, est, None if control is None else control.throttle)


def _wrap(fn: Callable[[BridgeCore, Any], list[Msg]]) -> Builder:
    return lambda core, value, _link: fn(core, value)


DS = mavlink
STREAMS: tuple[StreamSpec, ...] = (
    StreamSpec(mavlink.MAVLINK_MSG_ID_HEARTBEAT, None, _fixed(1000), _b_heartbeat),
    StreamSpec(mavlink.MAVLINK_MSG_ID_SYS_STATUS, None, _rate_param("MAV_STAT_HZ"),
               _b_sys_status, (DS.MAV_DATA_STREAM_EXTENDED_STATUS,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, None, _rate_param("MAV_STAT_HZ"),
               _b_extended, (DS.MAV_DATA_STREAM_EXTENDED_STATUS,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, None, _fixed(5000), _b_system_time,
               (DS.MAV_DATA_STREAM_EXTENDED_STATUS,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_NAMED_VALUE_INT, None, _param_period("MGR_STATUS_MS"),
               _b_thread_status, (DS.MAV_DATA_STREAM_EXTRA3,), frames=5),
    StreamSpec(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, "imu", _rate_param("MAV_IMU_HZ"), _b_highres,
               (DS.MAV_DATA_STREAM_RAW_SENSORS,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_SCALED_IMU, "imu", _fixed(None), _b_scaled),
    StreamSpec(mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, "gps", _rate_param("MAV_GPS_HZ"),
               _wrap(telemetry.gps_raw_int), (DS.MAV_DATA_STREAM_RAW_SENSORS,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_ATTITUDE, "estimator", _rate_param("MAV_ATT_HZ"),
               _wrap(telemetry.attitude), (DS.MAV_DATA_STREAM_EXTRA1,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, "estimator",
               _rate_param("MAV_ATT_HZ"), _wrap(telemetry.attitude_quaternion),
               (DS.MAV_DATA_STREAM_EXTRA1,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, "estimator",
               _rate_param("MAV_POS_HZ"), _wrap(telemetry.global_position_int),
               (DS.MAV_DATA_STREAM_POSITION,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, "estimator",
               _rate_param("MAV_POS_HZ"), _wrap(telemetry.local_position_ned),
               (DS.MAV_DATA_STREAM_POSITION,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_VFR_HUD, "estimator", _rate_param("MAV_HUD_HZ"),
               _b_vfr, (DS.MAV_DATA_STREAM_EXTRA2,)),
    # also when it changes (see Link.check_home); repeated so a ground station that connects
    # later gets it without asking (QGroundControl never asks)
    StreamSpec(mavlink.MAVLINK_MSG_ID_HOME_POSITION, None, _fixed(5000),
               _wrap(telemetry.home_position)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_RC_CHANNELS, "servo", _rate_param("MAV_RC_HZ"),
               _wrap(telemetry.rc_channels), (DS.MAV_DATA_STREAM_RC_CHANNELS,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, "servo", _rate_param("MAV_RC_HZ"),
               _wrap(telemetry.servo_output_raw), (DS.MAV_DATA_STREAM_RC_CHANNELS,)),
    StreamSpec(mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, "servo", _rate_param("MAV_STAT_HZ"),
               _wrap(telemetry.battery_status), (DS.MAV_DATA_STREAM_EXTENDED_STATUS,), frames=2),
)
STREAMS_BY_ID: dict[int, StreamSpec] = {s.msg_id: s for s in STREAMS}
# Beside an autopilot the vehicle's telemetry is the autopilot's: by default the companion sends
# only what is its own (its HEARTBEAT and its threads' status); the rest on request
COMPANION_STREAMS = frozenset({mavlink.MAVLINK_MSG_ID_HEARTBEAT,
                               mavlink.MAVLINK_MSG_ID_NAMED_VALUE_INT})
# NAMED_VALUE_FLOAT travels with the thread status (and GPS DOPs): one interval for both
STREAM_ALIASES = {mavlink.MAVLINK_MSG_ID_NAMED_VALUE_FLOAT: mavlink.MAVLINK_MSG_ID_NAMED_VALUE_INT}


def stream_for(msg_id: int) -> StreamSpec | None:
    return STREAMS_BY_ID.get(STREAM_ALIASES.get(msg_id, msg_id))


def streams_in_group(stream_id: int) -> list[StreamSpec]:
    if stream_id == mavlink.MAV_DATA_STREAM_ALL:
        return [s for s in STREAMS if s.groups]
    return [s for s in STREAMS if stream_id in s.groups]


MIN_FITTED_HZ = 0.2  # a radio too slow for even this gets it anyway (and the user is told)


def frame_bytes(spec: StreamSpec, signed: bool = False) -> int:
    """Bytes on the wire for one send of a stream (an upper bound: MAVLink 2 trims zeros)."""
    cls = mavlink.mavlink_map.get(spec.msg_id)
    payload = int(cls.unpacker.size) if cls is not None else 64
    return spec.frames * (payload + FRAME_OVERHEAD_BYTES + (SIGNATURE_BYTES if signed else 0))


def fit_to_line(rates_hz: list[float], sizes: list[int], fixed: list[bool],
                budget_bytes_s: float) -> list[float]:
    """Rates whose load fits `budget_bytes_s`: one cap for all non-fixed streams.

    Water-filling: streams slower than the cap keep their rate, faster ones are cut to it, so
    health and GPS at 1-2 Hz survive on a slow radio while attitude gives way first. Fixed
    streams (the heartbeat, a rate the user asked for) are never cut; the cap never goes
    below MIN_FITTED_HZ.
    """
    load = sum(r * s for r, s in zip(rates_hz, sizes, strict=True))
    if load <= budget_bytes_s:
        return list(rates_hz)
    remaining = budget_bytes_s - sum(r * s for r, s, f in zip(rates_hz, sizes, fixed, strict=True)
                                      if f)
    movable = sorted((r, s) for r, s, f in zip(rates_hz, sizes, fixed, strict=True)
                     if not f and r > 0)
    cap = MIN_FITTED_HZ
    below = 0.0  # load of the streams slower than the cap being tried
    for k, (rate, size) in enumerate(movable):
        above = sum(s for _r, s in movable[k:])
        if below + rate * above > remaining:
            cap = max(MIN_FITTED_HZ, (remaining - below) / above)
            break
        below += rate * size
    else:
        return list(rates_hz)
    return [r if f else min(r, cap) for r, f in zip(rates_hz, fixed, strict=True)]


@dataclass
class _StreamState:
    spec: StreamSpec
    override_us: int | None = None  # None: default period; -1: off; >0: interval
    next_due_ns: int = 0
    last_version: int = 0
    due_version: int | None = None  # slot version when the stream fell due
    sent: int = 0
    skipped: int = 0


@dataclass
class _SourceRate:
    """What the scheduler learnt of one data slot's write times (host ns, from its stamps)."""

    version: int = 0
    stamp_ns: int = 0
    mean_ns: float = 0.0  # mean time between two writes
    intervals: int = 0  # how many write intervals the mean is made of

    @property
    def period_ns(self) -> float:
        """The source's period, 0 while too few writes have been seen to trust it."""
        return self.mean_ns if self.intervals >= RATE_INTERVALS else 0.0

    def observe(self, version: int, stamp_ns: int) -> None:
        if self.version and version > self.version and stamp_ns > self.stamp_ns:
            n = version - self.version
            period = (stamp_ns - self.stamp_ns) / n
            self.mean_ns = period if not self.intervals else (
                self.mean_ns + (period - self.mean_ns) / 8)
            self.intervals += n
        if version != self.version:
            self.version, self.stamp_ns = version, stamp_ns

    def next_host_ns(self, host_now_ns: int) -> int | None:
        """When the next write is expected (host ns); None when the period is not known.

        A source late by more than a period (a device that went quiet) is expected again one
        period from now: looked at once per data period, not polled."""
        period = self.period_ns
        if not period:
            return None
        expected = self.stamp_ns + int(period)
        if host_now_ns - expected > period:
            return host_now_ns + int(period)
        return expected

    def first_after_host_ns(self, host_ns: float) -> float | None:
        """When the first write at or after `host_ns` is expected; None: period not known."""
        period = self.period_ns
        if not period:
            return None
        k = max(1, -(-(host_ns - self.stamp_ns) // period))  # whole periods, rounded up
        return self.stamp_ns + k * period


@dataclass
class StreamStats:
    sent: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)


class StreamScheduler:
    """Decides, for one link, which stream goes out when. Used by the link's sender only."""

    def __init__(self, core: BridgeCore, specs: Iterable[StreamSpec] = STREAMS, *,
                 line_bytes_s: float | None = None, signed: bool = False) -> None:
        self.core = core
        self.line_bytes_s = line_bytes_s  # a serial line's byte rate; None: a network
        self.signed = signed
        self._states = [_StreamState(s) for s in specs]
        self._by_id = {st.spec.msg_id: st for st in self._states}
        self.latencies_us: list[int] = []  # sample arrival -> message built, recent
        self.awaited: tuple[WaitableSlot[Any], int] | None = None
        self._periods_ms: list[float | None] = []
        self._periods_at_ns = 0
        self._lat_n = 0
        self._sources: dict[str, _SourceRate] = {}

    # ---------------------------------------------------------------- configuration
    def set_interval(self, msg_id: int, interval_us: int, now_ns: int) -> bool:
        """SET_MESSAGE_INTERVAL semantics: -1 off, 0 default, >0 interval in us."""
        spec = stream_for(msg_id)
        if spec is None:
            return False
        st = self._by_id[spec.msg_id]
        if interval_us == 0:
            st.override_us = None
        elif interval_us < 0:
            st.override_us = -1
        else:
            st.override_us = max(MIN_INTERVAL_US, int(interval_us))
        st.next_due_ns = now_ns
        self._periods_at_ns = 0  # recompute at the next service
        return True

    def interval_us(self, msg_id: int) -> int:
        """Current interval (us) for MESSAGE_INTERVAL: -1 off, 0 not a stream."""
        spec = stream_for(msg_id)
        if spec is None:
            return 0
        st = self._by_id[spec.msg_id]
        ms = self._period_ms(st)
        if self._periods_ms and self._periods_at_ns:  # the schedule in force (radio: fitted)
            ms = self._periods_ms[self._states.index(st)]
        return -1 if ms is None else int(ms * 1000)

    def _period_ms(self, st: _StreamState) -> float | None:
        if st.override_us is not None:
            return None if st.override_us < 0 else st.override_us / 1000.0
        if self.core.beside_autopilot and st.spec.msg_id not in COMPANION_STREAMS:
            return None
        ms = st.spec.default_ms(self.core)
        return float(ms) if ms else None

    def _fitted(self, periods: list[float | None]) -> list[float | None]:
        """The default schedule fitted to the radio's share (see `fit_to_line`)."""
        try:
            pct = float(self.core.ctx.params.get("MAV_RADIO_PCT"))
        except Exception:
            pct = 50.0
        rates = [1000.0 / p if p else 0.0 for p in periods]
        sizes = [frame_bytes(st.spec, self.signed) for st in self._states]
        fixed = [st.override_us is not None or st.spec.msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT
                 for st in self._states]
        assert self.line_bytes_s is not None
        fitted = fit_to_line(rates, sizes, fixed, self.line_bytes_s * pct / 100.0)
        return [1000.0 / r if r > 0 else None for r in fitted]

    def stats(self) -> StreamStats:
        return StreamStats({s.spec.name: s.sent for s in self._states},
                           {s.spec.name: s.skipped for s in self._states})

    # ---------------------------------------------------------------- running
    def service(self, now_ns: int, link: LinkSide, emit: Callable[[list[Msg]], None]) -> int:
        """Send what is due and fresh; returns how long (ns) the sender may sleep.

        When a due stream waits for a sample from a waitable slot, `awaited` says which slot
        and which version, so the sender can sleep on that slot and wake with the sample
        instead of polling.
        """
        wait_ns = IDLE_NS
        state = self.core.ctx.state
        scale = self.core.ctx.clock.scale
        host_now_ns = time.monotonic_ns()
        self.awaited = None
        awaited_at_ns = 0  # host ns: when the awaited slot's sample is expected
        awaited_slots: set[int] = set()
        if not self._periods_at_ns or now_ns - self._periods_at_ns >= PERIOD_REFRESH_NS:
            # periods come from parameters: re-read them a few times a second, not every wake-up
            periods = [self._period_ms(st) for st in self._states]
            if self.line_bytes_s is not None:
                periods = self._fitted(periods)
            for st, old, new in zip(self._states, self._periods_ms or periods, periods, strict=True):
                if new is not None and new != old and st.next_due_ns:
                    # a shorter period applies now, not after the rest of the old one
                    st.next_due_ns = min(st.next_due_ns, now_ns + int(new * 1e6))
            self._periods_ms = periods
            self._periods_at_ns = now_ns
        for st, period_ms in zip(self._states, self._periods_ms, strict=True):
            if period_ms is None:
                continue
            period_ns = int(period_ms * 1e6)
            if st.next_due_ns == 0:
                st.next_due_ns = now_ns
            if now_ns < st.next_due_ns:
                wait_ns = min(wait_ns, self._until_wake(st, period_ns, now_ns, host_now_ns))
                continue
            source = st.spec.source
            value: Any = None
            if source is not None:
                slot = getattr(state, source)
                value, version, stamp_ns = slot.read_versioned()
                if value is None:  # no data ever (no such device): look again next period
                    self._advance(st, period_ns, now_ns)
                    wait_ns = min(wait_ns, max(0, st.next_due_ns - now_ns))
                    continue
                if st.due_version is None:
                    # wait for the first sample *after* falling due, not the newest one seen:
                    # that one is on average half a data period old already
                    st.due_version = version if st.sent else min(version, st.last_version)
                    due_host_ns = host_now_ns - (now_ns - st.next_due_ns) / scale
                    if st.sent and version > st.last_version and stamp_ns >= due_host_ns:
                        st.due_version = version - 1  # the newest came after: it is fresh
                rate = self._sources.get(source)
                if rate is None:
                    rate = self._sources[source] = _SourceRate()
                rate.observe(version, stamp_ns)
                if version <= st.due_version:
                    if now_ns - st.next_due_ns >= period_ns:  # no fresh sample in a period
                        st.skipped += 1
                        link.counters.stale_skips += 1
                        st.due_version = None
                        self._advance(st, period_ns, now_ns)
                        wait_ns = min(wait_ns, max(0, st.next_due_ns - now_ns))
                        continue
                    # wake for the skip at the latest, and before that for the sample
                    wait_ns = min(wait_ns, st.next_due_ns + period_ns - now_ns)
                    expected = rate.next_host_ns(host_now_ns)
                    margin_ns = min(MARGIN_HOST_NS, int(rate.period_ns) // 4)
                    if expected is not None and expected + margin_ns > host_now_ns:
                        # not there yet: sleep on the queue until it should be
                        wait_ns = min(wait_ns, int((expected + margin_ns - host_now_ns) * scale))
                        continue
                    awaited_slots.add(id(slot))
                    if isinstance(slot, WaitableSlot) and (
                            self.awaited is None or (expected or 0) < awaited_at_ns):
                        self.awaited = (slot, version)
                        awaited_at_ns = expected or 0
                        wait_ns = min(wait_ns, AWAIT_NS)
                    else:
                        wait_ns = min(wait_ns, POLL_NS)
                    continue
                st.last_version = version
                st.due_version = None
            msgs = st.spec.build(self.core, value, link)
            if msgs:
                emit(msgs)
                st.sent += 1
                if value is not None and hasattr(value, "t_ns"):
                    self._note_latency(self.core.now_real_ns() - int(value.t_ns))
            self._advance(st, period_ns, now_ns)
            wait_ns = min(wait_ns, self._until_wake(st, period_ns, now_ns, host_now_ns))
        if len(awaited_slots) > 1:  # sleeping on one slot: look at the others often
            wait_ns = min(wait_ns, POLL_NS)
        return wait_ns

    def _until_wake(self, st: _StreamState, period_ns: int, now_ns: int, host_now_ns: int) -> int:
        """Clock ns until the sender should wake for stream `st`, which is not due yet.

        A data stream: when the first sample after it falls due should be there; a stream sent
        on time alone: its due time plus a slack, as it goes out with any wake-up after it."""
        until_ns = st.next_due_ns - now_ns
        if until_ns <= 0:
            return 0
        source = st.spec.source
        if source is None:
            return until_ns + min(TIME_SLACK_NS, period_ns // 10)
        rate = self._sources.get(source)
        if rate is None:
            return until_ns
        scale = self.core.ctx.clock.scale
        first = rate.first_after_host_ns(host_now_ns + until_ns / scale)
        if first is None:
            return until_ns
        margin_ns = min(MARGIN_HOST_NS, int(rate.period_ns) // 4)
        wake_ns = int((first + margin_ns - host_now_ns) * scale)
        return max(until_ns, min(wake_ns, until_ns + period_ns))

    @staticmethod
    def _advance(st: _StreamState, period_ns: int, now_ns: int) -> None:
        st.next_due_ns += period_ns
        if st.next_due_ns <= now_ns - period_ns:  # far behind (a pause): start again from now
            st.next_due_ns = now_ns + period_ns

    def _note_latency(self, latency_ns: int) -> None:
        us = max(0, latency_ns // 1000)
        if len(self.latencies_us) < LATENCY_RING:
            self.latencies_us.append(us)
        else:
            self.latencies_us[self._lat_n % LATENCY_RING] = us
        self._lat_n += 1
