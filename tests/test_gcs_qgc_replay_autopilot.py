"""QGroundControl's connection sequence replayed through the companion to a real ArduPlane SITL
(marked `sitl`).

tests/test_gcs_qgc_replay.py replays QGC's requests (docs/qgc-connection.md, from QGC's source:
master c5b560b8; QGC 5.x where it differs) against the bridge as the vehicle. Here the vehicle
is ArduPilot's own ArduPlane (`companion.sim.ardupilot.ArduPlaneSitl`, speed-up 5) on the
companion's pseudo-terminal cable, and QGC (system 255, component 190, MAVLink 2, QGC's
timeouts, the same `QgcLink` / `Replay` machinery) talks to the companion's UDP ground link
only. The system has two components: ArduPlane (1/1) and the companion (1/191,
gcs_bridge/router.py, docs/ground-stations.md "Beside an autopilot"). One SITL and one
companion serve the whole module; the tests run in QGC's order, each on the QGC session the
module fixture opened when ArduPlane's first HEARTBEAT came (MultiVehicleManager creates the
vehicle then).

What changes from the generic vehicle's sequence, because component 1's HEARTBEAT says
MAV_AUTOPILOT_ARDUPILOTMEGA and QGC loads its APM plugin:

* APMFirmwarePlugin::initializeStreamRates asks component 1 for HOME_POSITION and
  EXTENDED_SYS_STATE once a second (SET_MESSAGE_INTERVAL, sent once, no dialog). Its
  REQUEST_DATA_STREAM burst (QGC's APM stream-rate settings) is not replayed: it would set
  ArduPlane's rates on the companion's own cable, and at speed-up 5 flood this Python replay.
* PROTOCOL_VERSION: QGC 5.x skips it for ArduPilot (`vehicle->apmFirmware()` in
  _stateRequestProtocolVersion); master has no such step. ArduPlane is asked anyway, to record
  that it refuses at once.
* Parameters: ParameterManager sets `_tryftp` for ArduPilot and loads component 1's list as
  the MAVLink FTP file `@PARAM/param.pck` (FTPManager::download with checksize false, parsed by
  _parseParamFile), not with PARAM_REQUEST_LIST; while that runs it ignores component 1's
  PARAM_VALUE. refreshAllParameters() (also the editor's Refresh) does the same, so QGC never
  sends PARAM_REQUEST_LIST beside ArduPilot unless the FTP download fails: the companion's list
  comes only when asked of component 191 itself, which is what is replayed here.
* Mission, fence and rally are all read: ArduPlane's AUTOPILOT_VERSION has the FENCE and RALLY
  bits.
* QGC's MAVLink Console addresses the vehicle's component 1 (MAVLinkConsoleController), and
  Vehicle::_mavlinkMessageReceived shows SERIAL_CONTROL of any component of the vehicle; the
  companion answers console lines whatever their target, so QGC's console is the companion's.
  The Log Download page asks component 1 (ArduPlane's logs); the companion's log list is asked
  of 191 here as the brief of this file wants, though no QGC page would.

QGC converts integers from the C cast only for components whose own HEARTBEAT says ArduPilot
(APMFirmwarePlugin::adjustIncomingMavlinkMessage, `_ardupilotComponentMap`); 191's HEARTBEAT
says MAV_AUTOPILOT_INVALID, so QGC reads its integers bytewise, and the companion sends them so
(`test_9_...`; with the C cast an integer 1 showed as 1065353216).

Recorded, QGC copes: ArduPlane ACCEPTs REQUEST_MESSAGE for CAMERA_INFORMATION and
GIMBAL_MANAGER_INFORMATION and sends neither (no camera, no mount), so QGC's camera and gimbal
probes fail silently after their waits and retry; it refuses PROTOCOL_VERSION,
COMPONENT_METADATA and COMPONENT_INFORMATION (FAILED) at once; OpenFileRO of param.pck
announces more bytes than the file holds (QGC does not check the size there). The companion
numbers its log entries from 0 on a generic link, where QGC counts from 1 for an ArduPilot
vehicle (`_apmOneBased`); no QGC page asks 191 for logs, so it is not asserted.
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from test_gcs_qgc_replay import (
    ACK_TIMEOUT_S,
    CMD_REQUEST_CAMERA_INFORMATION,
    CONSOLE_REPLY_S,
    FTP_ACK,
    FTP_BURST,
    FTP_DATA_LEN,
    FTP_ERR_EOF,
    FTP_ERR_FAIL_ERRNO,
    FTP_NAK,
    FTP_OPEN_RO,
    FTP_READ,
    FTP_RESET,
    HEARTBEAT_LOST_S,
    LOG_LIST_FIRST_S,
    LOG_NEXT_S,
    MESSAGE_AFTER_ACK_S,
    METADATA_PARAMETER,
    MISSION_COUNT_S,
    MISSION_ITEM_S,
    MSG_AVAILABLE_MODES,
    MSG_CAMERA_INFORMATION,
    MSG_COMPONENT_INFORMATION,
    MSG_COMPONENT_METADATA,
    MSG_GIMBAL_MANAGER_INFORMATION,
    MSG_PROTOCOL_VERSION,
    PARAM_FIRST_S,
    PARAM_GAP_S,
    QGC_SYSID,
    FtpError,
    QgcFtp,
    QgcLink,
    Replay,
    c_string,
    check_general_json,
    header_of,
    heartbeat_qgc,
    mission_item,
    mission_reply,
    qgc_ftp_path,
    raw_fields,
)
from test_gcs_router_sitl import Companion

from gcs_bridge.dialect import mavlink

pytestmark = pytest.mark.sitl

AUTOPILOT = 1
COMPANION = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
ARDUPLANE_SYSID = 1  # ArduPlaneSitl's default (-I 0); the companion's [vehicle] id matches it
START_S = 30.0  # SITL start until ArduPlane's first HEARTBEAT (well under a second here)
SETTLE_S = 0.3  # after an answer: time for a wrong second answer (from 191) to show up
QGC_BEAT_S = 1.0  # MultiVehicleManager::_sendGCSHeartbeat

# ArduPilot's packed parameter file (AP_Filesystem_Param; QGC's ParameterManager::_parseParamFile)
PARAM_PCK = "@PARAM/param.pck"  # the path QGC opens: no scheme, so no leading "/"
PCK_MAGICS = (0x671B, 0x671C)  # plain, with defaults
PCK_VALUE = {1: "<b", 2: "<h", 3: "<i", 4: "<f"}  # AP_PARAM_INT8, INT16, INT32, FLOAT
PCK_FLOAT = 4


# --------------------------------------------------------------------- the module's QGC session
@dataclass
class Rig:
    """ArduPlane + the companion, and QGC's session with the vehicle they make."""

    companion: Companion
    qgc: Replay
    last_beat: float = field(default_factory=time.monotonic)

    @property
    def link(self) -> QgcLink:
        return self.qgc.link

    def beat(self) -> None:
        """QGC's own HEARTBEAT, once a second while the session lasts."""
        if time.monotonic() - self.last_beat >= QGC_BEAT_S:
            self.link.send(heartbeat_qgc())
            self.last_beat = time.monotonic()


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    link = QgcLink()
    companion: Companion | None = None
    try:
        companion = Companion(tmp_path_factory.mktemp("qgc-autopilot"), link.port,
                              vehicle_id=ARDUPLANE_SYSID)
        hb = link.wait(0, START_S, lambda m: m.get_type() == "HEARTBEAT"
                       and m.get_srcComponent() == AUTOPILOT)
        assert hb is not None, "no HEARTBEAT from component 1: QGC would never create the vehicle"
        link.send(heartbeat_qgc())  # MultiVehicleManager sends one at once, then 1 Hz
        yield Rig(companion, Replay(companion, link, hb))  # type: ignore[arg-type]
    finally:
        if companion is not None:
            companion.close()
        link.close()


@pytest.fixture
def qgc(rig: Rig) -> Replay:
    rig.beat()
    return rig.qgc


def from_companion(qgc: Replay, msg: Any) -> bool:
    _msg_id, system, component = header_of(msg)
    return system == qgc.sysid and component == COMPANION


def companion_replies(qgc: Replay, since: int, pred: Callable[[Any], bool]) -> list[Any]:
    """What component 191 sent after `since` (SETTLE_S more are awaited) that `pred` accepts."""
    qgc.link.gather(SETTLE_S)
    return [m for _t, m in qgc.link.inbox[since:] if from_companion(qgc, m) and pred(m)]


def command_to(qgc: Replay, comp: int, cmd: int, *params: float) -> tuple[int, Any]:
    """Replay.command for another component: (mark before sending, the ACK from `comp`)."""
    p = list(params) + [0.0] * (7 - len(params))
    mark = qgc.link.mark()
    qgc.link.send(mavlink.MAVLink_command_long_message(qgc.sysid, comp, cmd, 0, *p))
    ack = qgc.link.wait(mark, ACK_TIMEOUT_S, lambda m: m.get_type() == "COMMAND_ACK"
                        and m.command == cmd and header_of(m)[1:] == (qgc.sysid, comp))
    return mark, ack


def request_message_of(qgc: Replay, comp: int, msg_id: int) -> tuple[Any, Any]:
    """Vehicle::requestMessage to component `comp`: (COMMAND_ACK, the message or None)."""
    mark, ack = command_to(qgc, comp, mavlink.MAV_CMD_REQUEST_MESSAGE, msg_id)
    assert ack is not None, f"no COMMAND_ACK from component {comp} within {ACK_TIMEOUT_S} s"
    if ack.result != mavlink.MAV_RESULT_ACCEPTED:
        return ack, None
    msg = qgc.link.wait(mark, MESSAGE_AFTER_ACK_S, lambda m: header_of(m) == (
        msg_id, qgc.sysid, comp))
    return ack, msg


# --------------------------------------------------------------------- @PARAM/param.pck
class QgcParamFtp(QgcFtp):
    """FTPManager::download as ParameterManager::refreshAllParameters calls it for ArduPilot:
    `checksize` false. The length OpenFileRO announces then only drives the progress bar (whose
    first step stops the 5 s initial request timer); the file is what the bursts brought until
    the EOF NAK, holes filled with ReadFile. (QgcFtp.download checks the announced length, as
    QGC does for metadata files; ArduPlane announces more than param.pck holds.)"""

    def download_unsized(self, path: str) -> tuple[bytes, int, float]:
        """(the file, the length OpenFileRO announced, seconds until the first data)."""
        start = time.monotonic()
        name = path.encode()
        hdr, data = self.reply(self.send(FTP_OPEN_RO, size=len(name), data=name), FTP_OPEN_RO)
        if hdr[2] != FTP_ACK:
            raise FtpError(f"OpenFileRO {path!r} refused: error {data[0] if data else None}")
        if hdr[3] != 4:  # FTPManager::_openFileROAckOrNak, checked whatever `checksize` is
            raise FtpError(f"OpenFileRO ACK carries {hdr[3]} bytes, QGC wants the 4-byte length")
        session, announced = hdr[1], struct.unpack("<I", data[:4])[0]
        content = bytearray()
        holes: list[tuple[int, int]] = []
        offset = 0
        first_data_s: float | None = None
        mark = self.send(FTP_BURST, session=session, size=FTP_DATA_LEN, offset=0)
        deadline = time.monotonic() + 30.0  # bounds a misbehaving server
        while True:
            if time.monotonic() > deadline:
                raise FtpError("burst read does not end")
            # FTPManager ignores replies with stale sequence numbers
            hdr, data = self.reply(mark, FTP_BURST, exact_seq=False)
            mark = self.replay.link.after
            seq, sess, opcode, size, _req, burst_done, _pad, ofs = hdr
            if sess != session:
                continue
            if opcode == FTP_NAK:
                if data[0] != FTP_ERR_EOF:
                    raise FtpError(f"burst read NAK error {data[0]}")
                if seq != self.expected:  # EOF out of order: QGC asks again from where it is
                    self.expected = seq
                    mark = self.send(FTP_BURST, session=session, size=FTP_DATA_LEN, offset=offset)
                    continue
                break
            if first_data_s is None:
                first_data_s = time.monotonic() - start
            if ofs > offset:
                holes.append((offset, ofs - offset))
            elif ofs < offset:
                continue
            content.extend(bytes(max(0, ofs + size - len(content))))
            content[ofs:ofs + size] = data[:size]
            offset = ofs + size
            if burst_done:
                self.expected = seq
                mark = self.send(FTP_BURST, session=session, size=FTP_DATA_LEN, offset=offset)
            else:
                self.expected = (seq + 1) & 0xFFFF
        for hole_start, hole_count in holes:  # FTPManager::_fillMissingBlocksWorker
            at, left = hole_start, hole_count
            while left > 0:
                hdr, data = self.reply(self.send(FTP_READ, session=session,
                                                 size=min(left, FTP_DATA_LEN), offset=at), FTP_READ)
                if hdr[2] == FTP_NAK and data[0] == FTP_ERR_EOF:
                    break  # without the size check an EOF ends the filling
                if hdr[2] != FTP_ACK or hdr[7] != at or hdr[3] == 0:
                    raise FtpError(f"ReadFile at {at} failed")
                content[at:at + hdr[3]] = data[:hdr[3]]
                at, left = at + hdr[3], left - hdr[3]
        try:  # ACK, NAK or silence: QGC completes the download either way
            self.reply(self.send(FTP_RESET), FTP_RESET)
        except FtpError:
            pass
        return bytes(content), announced, first_data_s if first_data_s is not None else 0.0


def parse_param_pck(data: bytes) -> dict[str, tuple[int, float]]:
    """ParameterManager::_parseParamFile: name -> (AP type, value), or AssertionError where QGC
    would reject the file (and fall back to PARAM_REQUEST_LIST after its retries)."""
    assert len(data) >= 6, "shorter than the header"
    magic, num_params, total_params = struct.unpack_from("<HHH", data)
    assert magic in PCK_MAGICS, f"magic {magic:#06x}"
    assert num_params == total_params, f"{num_params} of {total_params} parameters (QGC asked all)"
    params: dict[str, tuple[int, float]] = {}
    name = b""
    pos = 6
    while True:
        while pos < len(data) and data[pos] == 0:  # padding
            pos += 1
        if pos >= len(data):
            break
        ptype, flags = data[pos] & 0x0F, data[pos] >> 4
        assert pos + 1 < len(data), "file ends in an entry's header"
        name_len, common_len = (data[pos + 1] >> 4) + 1, data[pos + 1] & 0x0F
        assert name_len + common_len <= 16, f"name of {name_len + common_len} characters"
        pos += 2
        name = name[:common_len] + data[pos:pos + name_len]
        pos += name_len
        assert ptype in PCK_VALUE, f"{name!r}: type {ptype} is out of range"
        fmt = PCK_VALUE[ptype]
        size = struct.calcsize(fmt)
        assert pos + size <= len(data), f"{name!r}: file ends in its value"
        value = struct.unpack_from(fmt, data, pos)[0]
        pos += size * (2 if flags & 1 else 1)  # a default value follows when flagged
        params[name.decode("ascii")] = (ptype, value)
        assert len(params) <= num_params, "more parameters in the file than its header says"
    assert len(params) == num_params, f"{len(params)} parameters, the header says {num_params}"
    return params


# ===================================================================== the sequence, in QGC's order
def test_0_heartbeats_of_arduplane_and_the_companion(rig: Rig) -> None:
    """MultiVehicleManager::_vehicleHeartbeatInfo creates the vehicle from component 1 (not
    ONBOARD_CONTROLLER); FirmwarePluginManager picks the APM plugin from
    MAV_AUTOPILOT_ARDUPILOTMEGA; APMFirmwarePlugin notes every component's autopilot field
    (191: not ArduPilot)."""
    qgc = rig.qgc
    hb = qgc.heartbeat
    assert qgc.sysid == ARDUPLANE_SYSID and qgc.sysid not in (0, QGC_SYSID)
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, \
        "step 0 (plugin): component 1 does not say ArduPilot, QGC would not load its APM plugin"
    assert hb.type == mavlink.MAV_TYPE_FIXED_WING, "step 0: not a fixed wing"
    beats: dict[int, Any] = {}
    deadline = time.monotonic() + HEARTBEAT_LOST_S
    mark = 0
    while time.monotonic() < deadline and len(beats) < 2:
        m = qgc.link.wait(mark, max(0.0, deadline - time.monotonic()),
                          lambda m: m.get_type() == "HEARTBEAT" and m.get_srcSystem() == qgc.sysid)
        if m is None:
            break
        mark = qgc.link.after
        beats[m.get_srcComponent()] = m
    assert set(beats) == {AUTOPILOT, COMPANION}, \
        f"step 0: HEARTBEATs of components {sorted(beats)} within {HEARTBEAT_LOST_S} s"
    ours = beats[COMPANION]
    assert ours.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER, \
        "step 0: component 191 would make QGC create a second vehicle"
    assert ours.autopilot == mavlink.MAV_AUTOPILOT_INVALID


def test_1_apm_plugin_asks_home_position_and_extended_sys_state(qgc: Replay) -> None:
    """APMFirmwarePlugin::initializeStreamRates: SET_MESSAGE_INTERVAL (1 s) for HOME_POSITION
    (ArduPilot sends it only on boot and arming) and, in recent QGC, EXTENDED_SYS_STATE; to
    component 1, sent once (no retry, no dialog). ArduPlane answers, the companion does not."""
    for msg_id in (mavlink.MAVLINK_MSG_ID_HOME_POSITION, mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE):
        mark, ack = qgc.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1_000_000)
        assert ack is not None, f"APM stream setup: SET_MESSAGE_INTERVAL({msg_id}) not ACKed"
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED, \
            f"APM stream setup: SET_MESSAGE_INTERVAL({msg_id}) refused ({ack.result})"
        assert not companion_replies(qgc, mark, lambda m: m.get_type() == "COMMAND_ACK"), \
            "the companion answered a command addressed to component 1"
    mark = qgc.link.mark()
    home = qgc.link.wait(mark, 5.0, lambda m: m.get_type() == "HOME_POSITION"
                         and qgc.from_autopilot(m))
    assert home is not None, "APM stream setup: no HOME_POSITION (map home, distance to home)"


def test_2_autopilot_version_is_arduplanes_alone(qgc: Replay) -> None:
    """InitialConnectStateMachine::_stateRequestAutopilotVersion: ACK and AUTOPILOT_VERSION from
    component 1; nothing from 191 (Vehicle::_handleCommandAck matches by component anyway)."""
    mark = qgc.link.mark()
    ack, msg = qgc.request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED, \
        f"step #2 AUTOPILOT_VERSION refused ({ack.result})"
    assert msg is not None, \
        f"step #2: AUTOPILOT_VERSION not within {MESSAGE_AFTER_ACK_S} s of the ACK"
    assert msg.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    # ArduPilot packs its version as major.minor.patch.type; QGC shows it and checks for updates
    assert (msg.flight_sw_version >> 24) & 0xFF >= 4, "step #2: firmware version"
    assert bytes(msg.flight_custom_version[:8]).decode("ascii").isalnum(), \
        "step #2: the git hash QGC shows (first 8 bytes as ASCII)"
    theirs = companion_replies(qgc, mark, lambda m: m.get_type() == "AUTOPILOT_VERSION" or (
        m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_REQUEST_MESSAGE))
    assert not theirs, f"step #2: component 191 answered a request addressed to 1: {theirs}"


def test_3_protocol_version_is_refused_at_once(qgc: Replay) -> None:
    """Not asked of ArduPilot (QGC 5.x skips the step for apmFirmware(); master has none):
    ArduPlane 4.7 refuses it (FAILED) within the ACK timeout, so asking would cost nothing."""
    ack, msg = qgc.request_message(MSG_PROTOCOL_VERSION)
    assert ack.result != mavlink.MAV_RESULT_ACCEPTED or msg is not None
    assert ack.result == mavlink.MAV_RESULT_FAILED


def test_4_camera_probe_is_acknowledged_at_once(qgc: Replay) -> None:
    """QGCCameraManager probes component 1 from its first HEARTBEAT, alternating command 521 and
    REQUEST_MESSAGE(259): both are ACKed within the timeout. ArduPlane (no camera) refuses 521
    but ACCEPTs 259 and then sends no CAMERA_INFORMATION: QGC's 1 s wait for the message fails
    and the probe retries silently (10 attempts, no dialog), costing a second each time."""
    _mark, ack = qgc.command(CMD_REQUEST_CAMERA_INFORMATION, 1)
    assert ack is not None, "camera probe: MAV_CMD_REQUEST_CAMERA_INFORMATION not acknowledged"
    assert ack.result != mavlink.MAV_RESULT_ACCEPTED
    mark, ack = qgc.command(mavlink.MAV_CMD_REQUEST_MESSAGE, MSG_CAMERA_INFORMATION)
    assert ack is not None, "camera probe: REQUEST_MESSAGE(259) not acknowledged"
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert qgc.link.wait(mark, MESSAGE_AFTER_ACK_S, lambda m: m.get_type() == "CAMERA_INFORMATION"
                         and qgc.from_autopilot(m)) is None


def test_5_available_modes_walk_is_complete(qgc: Replay) -> None:
    """StandardModes (master c5b560b8): REQUEST_MESSAGE(435, index) from 1 until mode_index >=
    number_modes; newer QGC (117ed905) asks all at once with param2 = 0. ArduPlane 4.7 answers
    both, with its named modes, through the companion."""
    index, names = 1, []
    while True:
        ack, msg = qgc.request_message(MSG_AVAILABLE_MODES, index)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED, \
            f"step #5 AVAILABLE_MODES index {index} refused ({ack.result}): modes stay unnamed"
        assert msg is not None, f"step #5: AVAILABLE_MODES index {index} not sent"
        custom, _props, number, mode_index, standard, name = raw_fields(msg, MSG_AVAILABLE_MODES)
        assert mode_index == index and number >= 1, f"step #5: index {mode_index} for {index}"
        assert standard != 0 or c_string(name), f"step #5: mode {custom} has no name"
        names.append(c_string(name))
        if mode_index >= number:
            break
        index += 1
        assert index <= 64, "step #5: the walk does not end"
    assert "MANUAL" in names and "AUTO" in names, names
    mark, ack = qgc.command(mavlink.MAV_CMD_REQUEST_MESSAGE, MSG_AVAILABLE_MODES, 0)
    assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED, "all modes at once"
    indices: set[int] = set()
    while len(indices) < len(names):
        msg = qgc.link.wait(mark, MESSAGE_AFTER_ACK_S, lambda m: qgc.from_autopilot(m)
                            and header_of(m)[0] == MSG_AVAILABLE_MODES)
        assert msg is not None, f"all modes asked, {len(indices)} of {len(names)} sent"
        mark = qgc.link.after
        fields = raw_fields(msg, MSG_AVAILABLE_MODES)
        assert fields[2] == len(names) and 1 <= fields[3] <= len(names)
        indices.add(fields[3])


def test_6_component_metadata_is_refused_at_once(qgc: Replay) -> None:
    """RequestMetaDataTypeStateMachine: COMPONENT_METADATA, then COMPONENT_INFORMATION; ArduPlane
    refuses both at once (QGC then uses the parameter metadata it ships for ArduPilot); 191 is
    not asked and does not answer for 1."""
    mark = qgc.link.mark()
    for msg_id in (MSG_COMPONENT_METADATA, MSG_COMPONENT_INFORMATION):
        ack, msg = qgc.request_message(msg_id)
        assert ack.result != mavlink.MAV_RESULT_ACCEPTED or msg is not None, \
            f"step #6/#7: REQUEST_MESSAGE({msg_id}) ACCEPTED but not sent"
        assert ack.result == mavlink.MAV_RESULT_FAILED
    theirs = companion_replies(qgc, mark, lambda m: header_of(m)[0] in (
        MSG_COMPONENT_METADATA, MSG_COMPONENT_INFORMATION) or m.get_type() == "COMMAND_ACK")
    assert not theirs, f"step #6: component 191 answered for component 1: {theirs}"


def test_7_parameters_over_mavlink_ftp(qgc: Replay) -> None:
    """ParameterManager for ArduPilot: FTPManager::download(1, "@PARAM/param.pck", checksize
    false), each reply within FTPManager's timeout, the first data within the 5 s initial
    request timer; _parseParamFile accepts the file and it holds ArduPlane's whole list."""
    content, announced, first_data_s = QgcParamFtp(qgc, AUTOPILOT).download_unsized(PARAM_PCK)
    assert announced > 0, \
        "step #10 (FTP): length 0 means no progress, QGC's 5 s timer would restart the load"
    assert first_data_s < PARAM_FIRST_S, f"step #10 (FTP): first data after {first_data_s:.1f} s"
    params = parse_param_pck(content)
    assert len(params) > 1000, f"step #10 (FTP): {len(params)} parameters"
    # the file agrees with ArduPlane's PARAM_VALUE (count, and values by C cast)
    some = [next(n for n, (t, _v) in params.items() if t != PCK_FLOAT),
            next(n for n, (t, _v) in params.items() if t == PCK_FLOAT)]
    for name in some:
        mark = qgc.link.mark()
        qgc.link.send(mavlink.MAVLink_param_request_read_message(qgc.sysid, AUTOPILOT,
                                                                 name.encode(), -1))
        m = qgc.link.wait(mark, 1.0, lambda m, name=name: m.get_type() == "PARAM_VALUE"
                          and m.param_id == name and qgc.from_autopilot(m))
        assert m is not None, f"{name} not read"
        assert m.param_count == len(params), "param.pck does not hold the whole list"
        assert m.param_value == pytest.approx(params[name][1], rel=1e-6)


def _list_from(qgc: Replay, comp: int) -> dict[str, tuple[int, float]]:
    """ParameterManager::refreshAllParameters(comp): PARAM_REQUEST_LIST to that component, then
    _handleParamValue's timers; name -> (param_type, param_value) of component `comp`."""
    mark = qgc.link.mark()
    qgc.link.send(mavlink.MAVLink_param_request_list_message(qgc.sysid, comp))
    values: dict[str, tuple[int, float]] = {}
    indices: set[int] = set()
    count: int | None = None
    timeout = PARAM_FIRST_S
    while count is None or len(indices) < count:
        m = qgc.link.wait(mark, timeout, lambda m: m.get_type() == "PARAM_VALUE"
                          and header_of(m)[1:] == (qgc.sysid, comp) and m.param_index != 65535)
        assert m is not None, (f"step #10 (list of {comp}): PARAM_VALUE {len(indices)} of {count} "
                               f"not within {timeout} s: QGC would re-request by index")
        mark = qgc.link.after
        timeout = PARAM_GAP_S
        count = m.param_count if count is None else count
        assert m.param_count == count and 0 <= m.param_index < count
        indices.add(m.param_index)
        values[m.param_id] = (m.param_type, m.param_value)
    return values


def test_8_companion_parameters_from_191(rig: Rig, qgc: Replay) -> None:
    """PARAM_REQUEST_LIST to (1, 191) (refreshAllParameters(191); QGC's own connect sequence
    never sends it beside ArduPilot, see the module docstring): the companion's whole list within
    QGC's timers, from 191 only (ArduPlane does not get the request)."""
    mark = qgc.link.mark()
    values = _list_from(qgc, COMPANION)
    assert set(values) == {s.name for s in rig.companion.rt.ctx.params.specs()}
    theirs = [m for _t, m in qgc.link.inbox[mark:] if m.get_type() == "PARAM_VALUE"
              and qgc.from_autopilot(m) and m.param_index != 65535]
    assert not theirs, "step #10: ArduPlane answered a list request addressed to 191"


def test_9_companion_integers_as_qgc_decodes_them(rig: Rig, qgc: Replay) -> None:
    """ParameterManager::_mavlinkParamUnionToVariant reads the four bytes as the declared type
    for every component APMFirmwarePlugin has not marked ArduPilot (by its HEARTBEAT)."""
    values = _list_from(qgc, COMPANION)
    wrong = {}
    for name, (ptype, value) in values.items():
        if ptype != mavlink.MAV_PARAM_TYPE_REAL32:
            shown = struct.unpack("<i", struct.pack("<f", value))[0]
            if shown != int(rig.companion.rt.ctx.params.get(name)):
                wrong[name] = (shown, rig.companion.rt.ctx.params.get(name))
    assert not wrong, f"parameter editor: QGC shows (value shown, value held) {wrong}"


def test_10_gimbal_probe_of_each_component(qgc: Replay) -> None:
    """GimbalController::_handleHeartbeat, after the parameters: REQUEST_MESSAGE(280) to every
    component that sends a HEARTBEAT, until GIMBAL_MANAGER_INFORMATION came or 6 were sent;
    each component ACKs at once. ArduPlane (no mount) ACCEPTs and sends nothing, so QGC asks it
    on 6 HEARTBEATs and stops; the companion refuses."""
    for comp in (AUTOPILOT, COMPANION):
        mark, ack = command_to(qgc, comp, mavlink.MAV_CMD_REQUEST_MESSAGE,
                               MSG_GIMBAL_MANAGER_INFORMATION)
        assert ack is not None, f"gimbal probe: no COMMAND_ACK from {comp} within {ACK_TIMEOUT_S} s"
        msg = qgc.link.wait(mark, MESSAGE_AFTER_ACK_S, lambda m, comp=comp: header_of(m) == (
            MSG_GIMBAL_MANAGER_INFORMATION, qgc.sysid, comp))
        if comp == COMPANION:
            assert ack.result != mavlink.MAV_RESULT_ACCEPTED or msg is not None, \
                "gimbal probe of 191: ACCEPTED but no GIMBAL_MANAGER_INFORMATION"
        else:
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED and msg is None


def test_11_mission_fence_rally_from_arduplane(qgc: Replay) -> None:
    """PlanManager::_requestList for each type AUTOPILOT_VERSION allows (ArduPlane: mission,
    fence and rally), items by MISSION_REQUEST_INT, MISSION_ACK at the end; all ArduPlane's."""
    _ack, version = qgc.request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert version is not None
    types = [mavlink.MAV_MISSION_TYPE_MISSION]
    if version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE:
        types.append(mavlink.MAV_MISSION_TYPE_FENCE)
    if version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY:
        types.append(mavlink.MAV_MISSION_TYPE_RALLY)
    assert len(types) == 3, "ArduPlane advertises fence and rally"
    start = qgc.link.mark()
    for mission_type in types:
        mark = qgc.link.mark()
        qgc.link.send(mavlink.MAVLink_mission_request_list_message(qgc.sysid, AUTOPILOT,
                                                                   mission_type))
        is_reply = mission_reply(mission_type)
        reply = qgc.link.wait(mark, MISSION_COUNT_S, lambda m, ok=is_reply: ok(m)
                              and qgc.from_autopilot(m))
        assert reply is not None, \
            f"step #13/#14: no MISSION_COUNT type {mission_type} within {MISSION_COUNT_S} s"
        assert reply.get_type() == "MISSION_COUNT", \
            f"step #13/#14: MISSION_ACK {reply.type}: QGC shows 'Mission transfer failed'"
        if mission_type == mavlink.MAV_MISSION_TYPE_MISSION:
            assert reply.count >= 1, "ArduPilot's mission starts with home (item 0)"
        for seq in range(reply.count):
            mark = qgc.link.mark()
            qgc.link.send(mavlink.MAVLink_mission_request_int_message(qgc.sysid, AUTOPILOT, seq,
                                                                      mission_type))
            is_item = mission_item(mission_type, seq)
            item = qgc.link.wait(mark, MISSION_ITEM_S, lambda m, ok=is_item: ok(m)
                                 and qgc.from_autopilot(m))
            assert item is not None, \
                f"step #13: item {seq} of type {mission_type} not within {MISSION_ITEM_S} s"
        qgc.link.send(mavlink.MAVLink_mission_ack_message(
            qgc.sysid, AUTOPILOT, mavlink.MAV_MISSION_ACCEPTED, mission_type))
    theirs = companion_replies(qgc, start, lambda m: m.get_type().startswith("MISSION_"))
    assert not theirs, f"step #13: component 191 answered a mission request for 1: {theirs}"


def _console(qgc: Replay, target: int, line: bytes) -> bytes:
    """MAVLinkConsoleController::_sendSerialData (device SHELL, flags RESPOND | EXCLUSIVE |
    MULTI, target fields), then what _receiveData would show until the prompt comes back."""
    flags = (mavlink.SERIAL_CONTROL_FLAG_EXCLUSIVE | mavlink.SERIAL_CONTROL_FLAG_RESPOND
             | mavlink.SERIAL_CONTROL_FLAG_MULTI)
    payload = struct.pack("<IHBBB70sBB", 0, 0, mavlink.SERIAL_CONTROL_DEV_SHELL, flags, len(line),
                          line.ljust(70, b"\0"), qgc.sysid, target)
    mark = qgc.link.mark()
    qgc.link.send_payload(mavlink.MAVLINK_MSG_ID_SERIAL_CONTROL, payload,
                          mavlink.MAVLink_serial_control_message.crc_extra)
    shown = b""
    deadline = time.monotonic() + CONSOLE_REPLY_S
    while not shown.endswith(b"> "):
        m = qgc.link.wait(mark, max(0.0, deadline - time.monotonic()),
                          lambda m: m.get_type() == "SERIAL_CONTROL"
                          and m.get_srcSystem() == qgc.sysid)
        assert m is not None, f"console: no prompt within {CONSOLE_REPLY_S} s, shown {shown!r}"
        mark = qgc.link.after
        assert from_companion(qgc, m), "console: a SERIAL_CONTROL from ArduPlane"
        assert m.device == mavlink.SERIAL_CONTROL_DEV_SHELL, "console: QGC shows device 10 only"
        assert 0 < m.count <= 70
        shown += bytes(m.data[:m.count])
    return shown


def test_12_console_is_the_companions(qgc: Replay) -> None:
    """The MAVLink Console page: QGC addresses component 1, the brief here 191; both times the
    companion's shell answers (ArduPlane has no shell device), echoing the line."""
    for target in (COMPANION, AUTOPILOT):
        shown = _console(qgc, target, b"uptime\n")
        assert b"uptime" in shown, f"console (target {target}): {shown!r}"


def test_13_companion_ftp_from_191(qgc: Replay) -> None:
    """FTPManager against 191: COMPONENT_METADATA of 191 names a file on 191 ([;comp=191]),
    which downloads the way QGC downloads metadata (sized) and is a valid general file; a
    missing file gets a one-byte NAK, ResetSessions an ACK, every reply seq = request seq + 1."""
    ack, msg = request_message_of(qgc, COMPANION, MSG_COMPONENT_METADATA)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED and msg is not None, \
        "COMPONENT_METADATA of 191"
    _t, _crc, uri_raw = raw_fields(msg, MSG_COMPONENT_METADATA)
    path, comp = qgc_ftp_path(c_string(uri_raw))
    assert comp == COMPANION, f"{c_string(uri_raw)!r}: QGC would fetch it from component {comp}"
    usable = check_general_json(json.loads(QgcFtp(qgc, comp).download(path)))
    assert METADATA_PARAMETER in usable
    ftp = QgcFtp(qgc, COMPANION)
    name = b"/qgc-replay/does-not-exist.json"
    hdr, data = ftp.reply(ftp.send(FTP_OPEN_RO, size=len(name), data=name), FTP_OPEN_RO)
    assert hdr[2] == FTP_NAK and hdr[3] == (2 if data[0] == FTP_ERR_FAIL_ERRNO else 1), \
        "FTP: a NAK QGC reads as 'Invalid Nak format'"
    hdr, _data = ftp.reply(ftp.send(FTP_RESET), FTP_RESET)
    assert hdr[2] == FTP_ACK


def test_14_companion_log_list_from_191(qgc: Replay) -> None:
    """LogDownloadController's listing (LOG_REQUEST_LIST 0..0xFFFF, 5 s for the first entry,
    0.5 s for each next) addressed to 191: the companion's flights, from 191, none from
    ArduPlane."""
    mark = qgc.link.mark()
    qgc.link.send(mavlink.MAVLink_log_request_list_message(qgc.sysid, COMPANION, 0, 0xFFFF))
    entries: dict[int, Any] = {}
    num_logs: int | None = None
    timeout = LOG_LIST_FIRST_S
    at = mark
    while num_logs is None or len(entries) < num_logs:
        m = qgc.link.wait(at, timeout, lambda m: m.get_type() == "LOG_ENTRY"
                          and m.get_srcSystem() == qgc.sysid)
        assert m is not None, \
            f"log list: LOG_ENTRY {len(entries)} of {num_logs} not within {timeout} s"
        at = qgc.link.after
        timeout = LOG_NEXT_S
        assert from_companion(qgc, m), "log list: ArduPlane answered a request addressed to 191"
        num_logs = m.num_logs if num_logs is None else num_logs
        if num_logs == 0:
            break
        assert m.num_logs == num_logs
        entries[m.id] = m
    assert num_logs is not None and num_logs >= 1, "the flight being recorded is listed"
    first = min(entries)
    assert sorted(entries) == list(range(first, first + num_logs)) and first in (0, 1)
    assert any(e.size > 0 for e in entries.values())
