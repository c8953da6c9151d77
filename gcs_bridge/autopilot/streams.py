"""What the link asks an autopilot to send, and asks again while it has not come.

One owner for the messages the companion needs and the parameter that sets each rate; the
link feeds it what arrives and sends what it returns. SET_MESSAGE_INTERVAL asks for one message
without touching the autopilot's settings; an ArduPilot that refuses it (ArduPlane 4.7.0-dev
does on its serial ports) is asked by stream group with REQUEST_DATA_STREAM, which sets that
port's ``SRn_*`` rates until it reboots: the link decides that and says so.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as apm

__all__ = ["REQUEST_EVERY_S", "STREAMS", "StreamRequests"]

REQUEST_EVERY_S = 5.0
"""A requested message that has not come is asked for again this often."""

STREAMS = {
    apm.MAVLINK_MSG_ID_RAW_IMU: "IMU_HZ",
    apm.MAVLINK_MSG_ID_HIGHRES_IMU: "IMU_HZ",
    apm.MAVLINK_MSG_ID_GPS_RAW_INT: "GPS_HZ",
    apm.MAVLINK_MSG_ID_ATTITUDE: "ATT_HZ",
    apm.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "POS_HZ",
    apm.MAVLINK_MSG_ID_RC_CHANNELS: "RC_HZ",
    apm.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: "RC_HZ",
    apm.MAVLINK_MSG_ID_SYSTEM_TIME: "TIME_HZ",
}
"""Message id -> the suffix of the link's parameter that sets its rate (Hz; 0 asks nothing)."""

_DATA_STREAM_OF = {
    apm.MAVLINK_MSG_ID_RAW_IMU: apm.MAV_DATA_STREAM_RAW_SENSORS,
    apm.MAVLINK_MSG_ID_GPS_RAW_INT: apm.MAV_DATA_STREAM_EXTENDED_STATUS,
    apm.MAVLINK_MSG_ID_RC_CHANNELS: apm.MAV_DATA_STREAM_RC_CHANNELS,
    apm.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: apm.MAV_DATA_STREAM_RC_CHANNELS,
    apm.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: apm.MAV_DATA_STREAM_POSITION,
    apm.MAVLINK_MSG_ID_ATTITUDE: apm.MAV_DATA_STREAM_EXTRA1,
    apm.MAVLINK_MSG_ID_SYSTEM_TIME: apm.MAV_DATA_STREAM_EXTRA3,
}
"""ArduPilot's stream group that carries each message (REQUEST_DATA_STREAM)."""


class StreamRequests:
    """Counts what arrives; says what to ask for next."""

    def __init__(self) -> None:
        self.arrived: dict[int, int] = {}
        self._at_request: dict[int, int] = {}
        self.data_streams = False
        """The autopilot refused SET_MESSAGE_INTERVAL: ask by group."""

    def count(self, msg_id: int) -> None:
        self.arrived[msg_id] = self.arrived.get(msg_id, 0) + 1

    def again(self) -> None:
        """Ask for everything at the next request (a new autopilot, a reboot)."""
        self._at_request.clear()

    def requests(self, out: Any, system: int, component: int, px4: bool,
                 rate_hz: Callable[[str], int]) -> list[Any]:
        """The messages to send now: each wanted message that has not come at half its rate
        since the last request (the first time: every one)."""
        first = not self._at_request
        groups: dict[int, int] = {}
        msgs: list[Any] = []
        for msg_id, suffix in STREAMS.items():
            if msg_id == apm.MAVLINK_MSG_ID_HIGHRES_IMU and not px4:
                continue  # ArduPilot's IMU is RAW_IMU; HIGHRES_IMU is PX4's
            if msg_id == apm.MAVLINK_MSG_ID_RAW_IMU and px4:
                continue  # PX4's RAW_IMU is raw counts
            hz = rate_hz(suffix)
            if hz <= 0:
                continue
            got = self.arrived.get(msg_id, 0) - self._at_request.get(msg_id, 0)
            if not first and got >= hz * REQUEST_EVERY_S / 2:
                continue
            if self.data_streams:
                group = _DATA_STREAM_OF.get(msg_id)
                if group is not None:
                    groups[group] = max(groups.get(group, 0), hz)
                continue
            msgs.append(out.command_long_encode(system, component,
                                                apm.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id,
                                                1e6 / hz, 0, 0, 0, 0, 0))
        msgs += [out.request_data_stream_encode(system, component, group, hz, 1)
                 for group, hz in groups.items()]
        for msg_id in STREAMS:
            self._at_request[msg_id] = self.arrived.get(msg_id, 0)
        return msgs
