"""COMMAND_LONG / COMMAND_INT: every command addressed to this vehicle gets a COMMAND_ACK.

Commands are decided in the receive thread but nothing is sent from there: the ACK and any
answer are posted to the link's sender queue. Commands that the thread manager carries out
(shutdown, reboot, restart a thread) are acknowledged when the manager replies, so ACCEPTED
means done. MAVSDK fills the parameters it does not use with NaN; they read as "not given".

Restarting one thread has no MAVLink command of its own: it is MAV_CMD_USER_1 (31010) with
param1 = thread id (the ids the thread status shows as `T<id>_...`).

MAV_CMD_PREFLIGHT_CALIBRATION with param5 = 2 (MAVProxy's ``ahrstrim``; what QGroundControl's
PX4 "Level Horizon" sends) is the level calibration: the estimator reads two seconds of IMU and sets
`EST_TRIM_ROLL/PITCH`; the ACK comes when it is done, with a STATUSTEXT giving the trims or
why it refused. Other calibrations (gyro, compass, six-position accelerometer, baro...) are
UNSUPPORTED: the estimator takes the gyro bias itself at every start.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from companion.watchdog import ManagerCommand
from gcs_bridge import telemetry
from gcs_bridge.dialect import MSG_ID_PROTOCOL_VERSION, Message, RxMessage, mavlink
from gcs_bridge.runtime_view import BridgeCore

log = logging.getLogger(__name__)

CMD_RESTART_THREAD = int(mavlink.MAV_CMD_USER_1)
DUPLICATE_WINDOW_S = 2.0
RECENT_MAX = 256

ACCEPTED = int(mavlink.MAV_RESULT_ACCEPTED)
INT32_MAX = 2**31 - 1
TEMPORARILY_REJECTED = int(mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
DENIED = int(mavlink.MAV_RESULT_DENIED)
UNSUPPORTED = int(mavlink.MAV_RESULT_UNSUPPORTED)
FAILED = int(mavlink.MAV_RESULT_FAILED)

#: Hook to start (True) / stop (False) the runtime's on-board logs; returns an error or None.
LoggingControl = Callable[[bool], "str | None"]


class CommandLink(Protocol):
    """The link a command arrived on, as the command handler needs it."""

    index: int

    def post(self, item: Any) -> bool: ...

    def can_provide(self, msg_id: int) -> bool: ...

    def request_message(self, msg_id: int, target: tuple[int, int]) -> bool: ...

    def set_interval(self, msg_id: int, interval_us: int) -> bool: ...

    def interval_us(self, msg_id: int) -> int: ...

    def notify(self, severity: int, text: str) -> None: ...


@dataclass(frozen=True)
class Command:
    """A COMMAND_LONG or COMMAND_INT reduced to what handlers need (NaN -> None)."""

    command: int
    params: tuple[float | None, ...]  # param1..param7 (COMMAND_INT x/y as floats)
    source: tuple[int, int]  # (system, component) to acknowledge
    confirmation: int = 0

    def p(self, i: int, default: float | None = None) -> float | None:
        v = self.params[i - 1]
        return default if v is None else v


def _param(value: Any) -> float | None:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    # NaN means "not given" (MAVLink's convention); an infinity is no usable value either, and
    # would raise in every int() below (a command that is never acknowledged)
    return f if math.isfinite(f) else None


def from_message(msg: RxMessage) -> Command:
    if msg.get_type() == "COMMAND_INT":
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z)
        confirmation = 0
    else:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                  msg.param7)
        confirmation = int(msg.confirmation)
    return Command(int(msg.command), tuple(_param(v) for v in params),
                   (msg.get_srcSystem(), msg.get_srcComponent()), confirmation)


def ack(cmd: Command, result: int, result_param2: int = 0) -> Message:
    return mavlink.MAVLink_command_ack_message(cmd.command, result, 0, result_param2,
                                               cmd.source[0], cmd.source[1])


class CommandHandler:
    """Executes commands for all links (shared; runs in each link's receive thread)."""

    def __init__(self, core: BridgeCore, *, logging_control: LoggingControl | None = None,
                 set_tlog_recording: Callable[[bool], None] | None = None) -> None:
        self.core = core
        self.logging_control = logging_control
        self.set_tlog_recording = set_tlog_recording
        self._recent: OrderedDict[tuple[int, int, int, int], tuple[float, int]] = OrderedDict()
        self._recent_lock = threading.Lock()  # receive threads and the manager's replies

    def handle(self, link: CommandLink, msg: RxMessage, *, quiet_unsupported: bool = False
               ) -> None:
        """`quiet_unsupported`: a command we do not support goes unacknowledged (beside an
        autopilot, one sent to every component is the autopilot's to acknowledge)."""
        cmd = from_message(msg)
        key = (link.index, cmd.source[0], cmd.source[1], cmd.command)
        now = time.monotonic()
        # a retransmission (confirmation > 0) of a command just executed is only re-acked
        if cmd.confirmation > 0:
            with self._recent_lock:
                seen = self._recent.get(key)
            if seen is not None and now - seen[0] < DUPLICATE_WINDOW_S:
                link.post([ack(cmd, seen[1])])
                return
        try:
            result = self._dispatch(link, cmd)
        except Exception:  # a handler's bug must still answer, and never reach the link
            log.exception("command %d from %d/%d", cmd.command, *cmd.source)
            result = FAILED
        if result is None:  # acknowledged later, by the manager's reply
            return
        if result == UNSUPPORTED and quiet_unsupported:
            return
        self._remember(key, now, result)
        link.post([ack(cmd, result)])

    def _remember(self, key: tuple[int, int, int, int], now: float, result: int) -> None:
        with self._recent_lock:
            self._recent[key] = (now, result)
            self._recent.move_to_end(key)
            while self._recent:  # drop what is too old to be retransmitted, and bound the rest
                oldest_key, (t, _r) = next(iter(self._recent.items()))
                if now - t <= DUPLICATE_WINDOW_S and len(self._recent) <= RECENT_MAX:
                    break
                del self._recent[oldest_key]

    # ------------------------------------------------------------------ the commands
    def _dispatch(self, link: CommandLink, cmd: Command) -> int | None:
        c = cmd.command
        if c == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = cmd.p(1)
            if msg_id is None or msg_id < 0 or msg_id != int(msg_id):
                return DENIED
            if int(msg_id) == mavlink.MAVLINK_MSG_ID_MESSAGE_INTERVAL:
                # the newer form of GET_MESSAGE_INTERVAL (QGC's MAVLink Inspector uses it)
                asked = cmd.p(2)
                if asked is None or asked != int(asked) or not 0 <= asked <= 0xFFFF:
                    return DENIED
                link.post([ack(cmd, ACCEPTED), mavlink.MAVLink_message_interval_message(
                    int(asked), link.interval_us(int(asked)))])
                return None
            if not link.can_provide(int(msg_id)):
                return UNSUPPORTED  # (QGC asks for component metadata this way, for instance)
            link.post([ack(cmd, ACCEPTED)])  # the protocol wants the ACK first
            self._remember((link.index, *cmd.source, c), time.monotonic(), ACCEPTED)
            link.request_message(int(msg_id), cmd.source)
            return None
        if c == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            link.post([ack(cmd, ACCEPTED)])
            link.request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, cmd.source)
            return None
        if c == mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION:
            link.post([ack(cmd, ACCEPTED)])
            link.request_message(MSG_ID_PROTOCOL_VERSION, cmd.source)
            return None
        if c == mavlink.MAV_CMD_GET_HOME_POSITION:
            if telemetry.home_of(self.core) is None:
                return TEMPORARILY_REJECTED
            link.post([ack(cmd, ACCEPTED)])
            link.request_message(mavlink.MAVLINK_MSG_ID_HOME_POSITION, cmd.source)
            return None
        if c == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(link, cmd)
        if c == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            msg_id = cmd.p(1)
            if msg_id is None or msg_id != int(msg_id) or not 0 <= msg_id <= 0xFFFF:
                return DENIED  # MESSAGE_INTERVAL carries a uint16 id
            link.post([ack(cmd, ACCEPTED), mavlink.MAVLink_message_interval_message(
                int(msg_id), link.interval_us(int(msg_id)))])
            return None
        if c == mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            return self._reboot_shutdown(link, cmd)
        if c == CMD_RESTART_THREAD:
            return self._restart_thread(link, cmd)
        if c == mavlink.MAV_CMD_PREFLIGHT_CALIBRATION:
            return self._calibrate(link, cmd)
        if c in (mavlink.MAV_CMD_LOGGING_START, mavlink.MAV_CMD_LOGGING_STOP):
            return self._logging(link, cmd, c == mavlink.MAV_CMD_LOGGING_START)
        return UNSUPPORTED

    def _set_interval(self, link: CommandLink, cmd: Command) -> int:
        msg_id, interval = cmd.p(1), cmd.p(2)
        if msg_id is None or interval is None or msg_id != int(msg_id):
            return DENIED
        if interval > INT32_MAX:
            # MESSAGE_INTERVAL reports the interval as int32: a longer one could be set but
            # never reported back (found by bench/fuzz_bench.py); 35 minutes is the ceiling
            return DENIED
        if not link.set_interval(int(msg_id), int(interval)):
            return UNSUPPORTED
        return ACCEPTED

    def _reboot_shutdown(self, link: CommandLink, cmd: Command) -> int | None:
        # param1: autopilot (1 reboot, 2 shutdown); param2: onboard computer. This bridge is
        # both, so either one asks the runtime to stop (reboot: the runtime is restarted);
        # beside an autopilot it is the onboard computer only, and param1 is the autopilot's.
        asked = (cmd.p(2, 0.0),) if self.core.beside_autopilot else (cmd.p(1, 0.0), cmd.p(2, 0.0))
        actions = {int(v) for v in asked if v is not None}
        actions.discard(0)
        if not actions:
            return ACCEPTED  # "do nothing" for both is a valid request
        if not actions <= {1, 2}:
            return UNSUPPORTED  # bootloader, keep-in-bootloader, power-off hardware...
        kind = "stop" if 2 in actions else "reboot"
        return self._post_manager(link, cmd, ManagerCommand(kind, reason=0))

    def _restart_thread(self, link: CommandLink, cmd: Command) -> int | None:
        tid = cmd.p(1)
        if tid is None or tid != int(tid):
            return DENIED
        if self.core.manager.find(int(tid)) is None:
            link.notify(mavlink.MAV_SEVERITY_WARNING, f"restart: no thread {int(tid)}")
            return DENIED
        return self._post_manager(link, cmd, ManagerCommand("restart_thread", int(tid)))

    def _calibrate(self, link: CommandLink, cmd: Command) -> int | None:
        # param1 gyro, 2 magnetometer, 3 ground pressure, 4 radio, 5 accelerometer (2: board
        # level), 6 compass/motor, 7 ESC or airspeed; 0 everywhere asks for nothing
        asked = {i: v for i in range(1, 8) if (v := cmd.p(i, 0.0)) not in (None, 0.0)}
        if not asked:
            return ACCEPTED
        if asked != {5: 2.0}:
            link.notify(mavlink.MAV_SEVERITY_WARNING,
                        "calibration: only the level calibration (param5 = 2) is supported")
            return UNSUPPORTED
        return self._post_manager(link, cmd, ManagerCommand("calibrate_level"))

    def _post_manager(self, link: CommandLink, cmd: Command, mc: ManagerCommand) -> int | None:
        key = (link.index, cmd.source[0], cmd.source[1], cmd.command)

        def reply(ok: bool, reason: str) -> None:  # runs in the manager's (main) thread
            result = ACCEPTED if ok else FAILED
            self._remember(key, time.monotonic(), result)
            link.post([ack(cmd, result)])
            if not ok:
                link.notify(mavlink.MAV_SEVERITY_WARNING, f"command {cmd.command}: {reason}")
            elif reason:  # what a long-running command found (a calibration's result)
                link.notify(mavlink.MAV_SEVERITY_INFO, reason)

        posted = ManagerCommand(mc.kind, mc.thread, mc.reason, reply)
        if not self.core.manager.post(posted):
            return TEMPORARILY_REJECTED
        log.info("command %d from %s posted to the manager (%s)", cmd.command, cmd.source, mc.kind)
        return None

    def _logging(self, link: CommandLink, cmd: Command, start: bool) -> int:
        if self.set_tlog_recording is not None:
            self.set_tlog_recording(start)
        if self.logging_control is not None:
            try:
                error = self.logging_control(start)
            except Exception as exc:  # the hook's failure is reported, not raised
                error = f"{type(exc).__name__}: {exc}"
            if error:
                link.notify(mavlink.MAV_SEVERITY_WARNING, f"logging: {error}")
                return FAILED
        return ACCEPTED
