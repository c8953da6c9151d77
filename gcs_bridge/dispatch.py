"""What the bridge does with each message a ground station sends (receive side).

Runs in a link's receive thread, after the signing policy let the message through. Nothing is
sent from here: answers are posted to the link's sender queue (or, for parameter changes, to
every link by the registry's change notification).

Calls go one way: the link calls the dispatcher, the dispatcher calls the link's services. The
dispatcher sees the link only as `DispatchLink`, so nothing here imports `gcs_bridge.link`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Protocol

from companion.core.state import HorizonMeasurement
from gcs_bridge import status
from gcs_bridge.commands import CommandHandler, CommandLink
from gcs_bridge.dialect import Identity, Message, RxMessage, mavlink
from gcs_bridge.params import codec as param_codec
from gcs_bridge.params.protocol import ParamProtocol
from gcs_bridge.runtime_view import BridgeCore
from gcs_bridge.services.link_services import LinkServices

log = logging.getLogger(__name__)


class DispatchLink(CommandLink, Protocol):
    """The link a message arrived on, as the handlers need it (`gcs_bridge.link.Link` is one):
    the dispatcher is called by the link and answers through it without importing it."""

    text_ids: status.StatusTextIds
    services: LinkServices

    @property
    def identity(self) -> Identity: ...

    def post_param(self, index: int) -> bool: ...

    def start_param_list(self) -> bool: ...

    def note_peer(self, system: int, component: int, mav_type: int) -> None: ...

    def data_stream(self, stream_id: int, rate_hz: int, start: bool) -> None: ...

    def refuse(self, msg: RxMessage, why: str) -> None: ...


class Dispatcher:
    """Shared by all links; holds no per-link state."""

    def __init__(self, core: BridgeCore, params: ParamProtocol, commands: CommandHandler) -> None:
        self.core = core
        self.params = params
        self.commands = commands
        m = mavlink
        self._handlers: dict[int, Callable[[DispatchLink, RxMessage], None]] = {
            m.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            m.MAVLINK_MSG_ID_PARAM_REQUEST_LIST: self._param_request_list,
            m.MAVLINK_MSG_ID_PARAM_REQUEST_READ: self._param_request_read,
            m.MAVLINK_MSG_ID_PARAM_SET: self._param_set,
            m.MAVLINK_MSG_ID_COMMAND_LONG: self._command,
            m.MAVLINK_MSG_ID_COMMAND_INT: self._command,
            m.MAVLINK_MSG_ID_REQUEST_DATA_STREAM: self._request_data_stream,
            m.MAVLINK_MSG_ID_PING: self._ping,
            m.MAVLINK_MSG_ID_TIMESYNC: self._timesync,
            m.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL: self._ftp,
            m.MAVLINK_MSG_ID_LOG_REQUEST_LIST: self._log(lambda s: s.log_request_list),
            m.MAVLINK_MSG_ID_LOG_REQUEST_DATA: self._log(lambda s: s.log_request_data),
            m.MAVLINK_MSG_ID_LOG_REQUEST_END: self._log(lambda s: s.log_request_end),
            m.MAVLINK_MSG_ID_LOG_ERASE: self._log(lambda s: s.log_erase),
            m.MAVLINK_MSG_ID_SERIAL_CONTROL: self._serial_control,
            m.MAVLINK_MSG_ID_MISSION_REQUEST_LIST: self._mission_request_list,
            m.MAVLINK_MSG_ID_MISSION_COUNT: self._mission_upload,
            m.MAVLINK_MSG_ID_SETUP_SIGNING: self._setup_signing,
            m.MAVLINK_MSG_ID_ATTITUDE: self._horizon_attitude,
            m.MAVLINK_MSG_ID_NAMED_VALUE_FLOAT: self._horizon_quality,
        }
        # horizon attitude from the camera component, waiting for its HZN_QUAL companion
        self._pending_horizon: tuple[int, int, float, float] | None = None

    def handle(self, link: DispatchLink, msg: RxMessage) -> None:
        handler = self._handlers.get(msg.get_msgId())
        if handler is None:
            return
        try:
            handler(link, msg)
        except Exception:  # a handler bug must not take the link down; it is logged loudly
            log.exception("link %d: handling %s failed", link.index, msg.get_type())

    # ------------------------------------------------------------------ horizon aiding
    def _horizon_attitude(self, link: DispatchLink, msg: RxMessage) -> None:
        """ATTITUDE from the camera component (100) is a horizon-detector estimate (see
        docs/horizon.md): roll and pitch only; its quality follows as NAMED_VALUE_FLOAT HZN_QUAL."""
        if msg.get_srcComponent() != mavlink.MAV_COMP_ID_CAMERA:
            return
        if not (math.isfinite(msg.roll) and math.isfinite(msg.pitch)):
            return
        previous = self._pending_horizon
        if previous is not None:
            self._write_horizon(previous[1], previous[2], previous[3], 0.5)
        self._pending_horizon = (msg.time_boot_ms, self.core.now_real_ns(), msg.roll, msg.pitch)

    def _horizon_quality(self, link: DispatchLink, msg: RxMessage) -> None:
        pending = self._pending_horizon
        if (pending is None or msg.get_srcComponent() != mavlink.MAV_COMP_ID_CAMERA
                or msg.name.rstrip("\x00") != "HZN_QUAL" or msg.time_boot_ms != pending[0]):
            return
        self._pending_horizon = None
        quality = msg.value if math.isfinite(msg.value) else 0.0
        self._write_horizon(pending[1], pending[2], pending[3], max(0.0, min(1.0, quality)))

    def _write_horizon(self, t_ns: int, roll: float, pitch: float, quality: float) -> None:
        self.core.ctx.state.horizon.write(
            HorizonMeasurement(t_ns, float(roll), float(pitch), quality, "mavlink"))

    # ------------------------------------------------------------------ helpers
    def _for_us(self, target_system: int, target_component: int) -> bool:
        return (target_system in (0, self.core.sysid)
                and target_component in (0, self.core.compid))

    def _shared_request(self, msg: RxMessage) -> bool:
        """Beside an autopilot, a request to every component (target component 0) that we
        cannot serve is the autopilot's to answer: we stay silent rather than answer "no such
        parameter" or "unsupported" before or after it."""
        return self.core.beside_autopilot and msg.target_component == 0

    def _param_error(self, msg: RxMessage, name: str, index: int, error: int) -> Message:
        return mavlink.MAVLink_param_error_message(
            msg.get_srcSystem(), msg.get_srcComponent(), name.encode("ascii", "replace")[:16],
            max(-1, min(index, 32767)), error)

    # ------------------------------------------------------------------ handlers
    def _heartbeat(self, link: DispatchLink, msg: RxMessage) -> None:
        link.note_peer(msg.get_srcSystem(), msg.get_srcComponent(), msg.type)

    def _param_request_list(self, link: DispatchLink, msg: RxMessage) -> None:
        if self._for_us(msg.target_system, msg.target_component):
            link.start_param_list()

    def _param_request_read(self, link: DispatchLink, msg: RxMessage) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        index = self.params.lookup(msg.param_id, int(msg.param_index))
        if index is None:
            if self._shared_request(msg):
                return
            link.post([self._param_error(msg, msg.param_id, int(msg.param_index),
                                         mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)])
            return
        link.post_param(index)

    def _param_set(self, link: DispatchLink, msg: RxMessage) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        raw = param_codec.raw_value_of(msg)
        outcome = self.params.apply_set(msg.param_id, raw, int(msg.param_type),
                                        bytewise=link.identity.bytewise)
        if outcome.ok:
            if not outcome.changed and outcome.index is not None:
                link.post_param(outcome.index)  # a change is announced to every link instead
            if outcome.changed and outcome.reason:
                link.notify(mavlink.MAV_SEVERITY_NOTICE, f"{outcome.name}: {outcome.reason}")
            return
        if outcome.index is None and self._shared_request(msg):
            return  # the autopilot's parameter, not ours
        text = f"{outcome.name}: {outcome.reason}"
        log.info("link %d: refused PARAM_SET %s", link.index, text)
        # PARAM_ERROR first: a client that understands it (MAVSDK) stops at once instead of
        # taking the unchanged PARAM_VALUE for a lost set and retrying
        link.post([self._param_error(msg, outcome.name,
                                     -1 if outcome.index is None else outcome.index,
                                     outcome.error)])
        link.post(status.statustext(mavlink.MAV_SEVERITY_WARNING, text, link.text_ids))
        if outcome.index is not None:
            link.post_param(outcome.index)  # the unchanged value, as the protocol asks

    def _command(self, link: DispatchLink, msg: RxMessage) -> None:
        if self._for_us(msg.target_system, msg.target_component):
            self.commands.handle(link, msg, quiet_unsupported=self._shared_request(msg))

    def _request_data_stream(self, link: DispatchLink, msg: RxMessage) -> None:
        if self._for_us(msg.target_system, msg.target_component):
            link.data_stream(int(msg.req_stream_id), int(msg.req_message_rate),
                             bool(msg.start_stop))

    def _ping(self, link: DispatchLink, msg: RxMessage) -> None:
        if msg.target_system == 0 and msg.target_component == 0:  # a request, not an answer
            link.post([mavlink.MAVLink_ping_message(msg.time_usec, msg.seq, msg.get_srcSystem(),
                                                    msg.get_srcComponent())])

    def _timesync(self, link: DispatchLink, msg: RxMessage) -> None:
        if msg.tc1 == 0:  # a request
            link.post([mavlink.MAVLink_timesync_message(self.core.now_real_ns(), msg.ts1)])

    def _ftp(self, link: DispatchLink, msg: RxMessage) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        link.services.ftp_request(msg)

    def _log(self, pick: Callable[[LinkServices], Callable[[RxMessage], None]]
             ) -> Callable[[DispatchLink, RxMessage], None]:
        """A LOG_* handler: addressed to us, then the link's log service."""
        def handle(link: DispatchLink, msg: RxMessage) -> None:
            if self._for_us(msg.target_system, msg.target_component):
                pick(link.services)(msg)
        return handle

    def _serial_control(self, link: DispatchLink, msg: RxMessage) -> None:
        # SERIAL_CONTROL has no target fields in pymavlink 2.4.50's common dialect: a console
        # message reaching this link is for this vehicle
        link.services.serial_control(msg)

    def _mission_request_list(self, link: DispatchLink, msg: RxMessage) -> None:
        if self._for_us(msg.target_system, msg.target_component):
            # no mission service: an empty list ends the GCS's download at once
            link.post([mavlink.MAVLink_mission_count_message(
                msg.get_srcSystem(), msg.get_srcComponent(), 0,
                getattr(msg, "mission_type", 0))])

    def _mission_upload(self, link: DispatchLink, msg: RxMessage) -> None:
        if self._for_us(msg.target_system, msg.target_component):
            link.post([mavlink.MAVLink_mission_ack_message(
                msg.get_srcSystem(), msg.get_srcComponent(), mavlink.MAV_MISSION_UNSUPPORTED,
                getattr(msg, "mission_type", 0))])

    def _setup_signing(self, link: DispatchLink, msg: RxMessage) -> None:
        # the key comes from the key file only; a key sent over a link is never used nor
        # passed on (and never logged: see tlog)
        link.refuse(msg, "SETUP_SIGNING is not accepted over MAVLink")
