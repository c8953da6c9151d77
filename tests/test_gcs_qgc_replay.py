"""A replay of QGroundControl's connection requests against the bridge (QGC itself does not run).

docs/qgc-connection.md lists, from QGC's source (master c5b560b8, 2026-02-19; QGC 5.x where it
differs), every request QGC sends when it first hears a vehicle, what it waits for and for how
long. Each test here sends one step of that sequence the way QGC sends it (system 255 component
190, MAVLink 2, the same message fields, FTP sequence numbering and SERIAL_CONTROL extension
fields) to a `SyntheticVehicle` over UDP loopback, and checks that every answer QGC waits for
arrives within QGC's first-try timeout, with the fields QGC reads. The tests run in QGC's order.

Messages that pymavlink 2.4.50 does not know (PROTOCOL_VERSION, COMPONENT_INFORMATION,
COMPONENT_METADATA, AVAILABLE_MODES) are decoded from the frame bytes here, and their CRC is
checked with the CRC_EXTRA that QGC's MAVLink library uses: QGC drops a frame whose CRC_EXTRA is
wrong without a word.

Component metadata, the MAVLink FTP download, the Log Download page and the MAVLink Console
each have their own test, so a failure names the QGC page that would break.
"""

from __future__ import annotations

import gzip
import io
import json
import lzma
import math
import re
import select
import socket
import struct
import tarfile
import time
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port
from support.synthetic_vehicle import SyntheticVehicle

from companion import __version__
from companion.core.params import int_param
from gcs_bridge.dialect import mavlink

# --------------------------------------------------------------------- QGC's numbers
QGC_SYSID, QGC_COMPID = 255, 190  # QGC's default system id; MAV_COMP_ID_MISSIONPLANNER
AUTOPILOT_COMP = 1
# Vehicle.h / Vehicle.cc (_mavCommandAckTimeoutMSecs; the message wait after an ACK)
ACK_TIMEOUT_S = 3.0
MESSAGE_AFTER_ACK_S = 1.0
HEARTBEAT_LOST_S = 3.5  # VehicleLinkManager.h: _heartbeatMaxElpasedMSecs
PARAM_FIRST_S = 5.0  # ParameterManager: _initialRequestTimeoutTimer
PARAM_GAP_S = 3.0  # ParameterManager: _waitingParamTimeoutTimer
MISSION_COUNT_S = 1.5  # PlanManager: _ackTimeoutMilliseconds
MISSION_ITEM_S = 0.25  # PlanManager: _retryTimeoutMilliseconds
FTP_REPLY_S = 1.0  # FTPManager: _ackOrNakTimeoutMsecs
LOG_LIST_FIRST_S = 5.0  # LogDownloadController: kRequestLogListTimeoutMs
LOG_NEXT_S = 0.5  # LogDownloadController: kTimeOutMs
CONSOLE_REPLY_S = 3.0  # QGC's console has no timeout: a user waits about this long

MSG_PROTOCOL_VERSION = 300
MSG_COMPONENT_INFORMATION = 395
MSG_COMPONENT_METADATA = 397
MSG_AVAILABLE_MODES = 435
MSG_CAMERA_INFORMATION = 259
MSG_GIMBAL_MANAGER_INFORMATION = 280
CMD_REQUEST_CAMERA_INFORMATION = 521

# message id -> (payload layout in wire order, CRC_EXTRA) for what pymavlink 2.4.50 lacks
RAW_LAYOUTS: dict[int, tuple[str, int]] = {
    MSG_PROTOCOL_VERSION: ("<HHH8s8s", 217),
    MSG_COMPONENT_INFORMATION: ("<III100s100s", 0),
    MSG_COMPONENT_METADATA: ("<II100s", 182),
    MSG_AVAILABLE_MODES: ("<IIBBB35s", 134),
}

# MAVLink FTP (QGC's src/MAVLink/MAVLinkFTP.h)
FTP_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst, pad, offset
FTP_DATA_LEN = 251 - FTP_HEADER.size
FTP_RESET, FTP_OPEN_RO, FTP_READ, FTP_BURST = 2, 4, 5, 15
FTP_ACK, FTP_NAK = 128, 129
FTP_ERR_EOF, FTP_ERR_FAIL_ERRNO = 6, 2

# COMP_METADATA_TYPE
METADATA_PARAMETER = 1

# FactMetaData: known type names, and the JSON type of every key it validates
QGC_TYPES = {"uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64", "float",
             "double", "string", "bool", "elapsedseconds", "custom"}
QGC_TYPE_OF_PARAM = {
    mavlink.MAV_PARAM_TYPE_UINT8: "uint8", mavlink.MAV_PARAM_TYPE_INT8: "int8",
    mavlink.MAV_PARAM_TYPE_UINT16: "uint16", mavlink.MAV_PARAM_TYPE_INT16: "int16",
    mavlink.MAV_PARAM_TYPE_UINT32: "uint32", mavlink.MAV_PARAM_TYPE_INT32: "int32",
    mavlink.MAV_PARAM_TYPE_REAL32: "float",
}
STRING_KEYS = ("name", "type", "shortDesc", "longDesc", "units", "category", "group",
               "enumValues", "enumStrings")
NUMBER_KEYS = ("decimalPlaces", "min", "max", "userMin", "userMax")
BOOL_KEYS = ("control", "qgcRebootRequired", "rebootRequired", "volatile")
ARRAY_KEYS = ("bitmask", "values")

# an int32 above 2**24: a C-cast float cannot carry it, QGC's bytewise decoding can
BIG = 2**30 + 7
EXTRA = [int_param("TST_BIG", BIG, -(2**31), 2**31 - 1, "", "int32 beyond float precision")]


# --------------------------------------------------------------------- QGC's side of the link
class QgcLink:
    """QGC's end of a UDP link: system 255 component 190, MAVLink 2, every frame kept in order.

    `mark()` returns a position in the inbox; `wait(mark, ...)` looks only at what arrived after
    it, so an answer is matched to the request sent after the mark; `after` is the position just
    past the message `wait` returned, to go on reading a stream of answers.
    """

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", free_udp_port()))
        self.mav = mavlink.MAVLink(None, QGC_SYSID, QGC_COMPID)
        self.mav.robust_parsing = True
        self.inbox: list[tuple[float, Any]] = []  # (arrival time, message)
        self.dest: tuple[str, int] | None = None
        self.after = 0  # inbox position just after the message `wait` returned last

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def close(self) -> None:
        self.sock.close()

    def _pump(self, timeout_s: float) -> None:
        ready, _, _ = select.select([self.sock], [], [], max(0.0, timeout_s))
        while ready:
            data, addr = self.sock.recvfrom(65535)
            self.dest = addr
            now = time.monotonic()
            for msg in self.mav.parse_buffer(data) or []:
                if msg.get_type() != "BAD_DATA":
                    self.inbox.append((now, msg))
            ready, _, _ = select.select([self.sock], [], [], 0)

    def mark(self) -> int:
        self._pump(0)
        return len(self.inbox)

    def wait(self, since: int, timeout_s: float, pred: Callable[[Any], bool]) -> Any:
        """The first message after `since` that satisfies `pred`, waiting up to timeout_s."""
        deadline = time.monotonic() + timeout_s
        checked = since
        while True:
            for i in range(checked, len(self.inbox)):
                msg = self.inbox[i][1]
                if pred(msg):
                    self.after = i + 1
                    return msg
            checked = len(self.inbox)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._pump(remaining)

    def gather(self, duration_s: float) -> list[tuple[float, Any]]:
        """Everything that arrives during duration_s."""
        start = self.mark()
        deadline = time.monotonic() + duration_s
        while (remaining := deadline - time.monotonic()) > 0:
            self._pump(remaining)
        return self.inbox[start:]

    def send(self, msg: Any) -> None:
        assert self.dest is not None, "nothing heard from the vehicle yet"
        frame = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) & 0xFF
        self.sock.sendto(frame, self.dest)

    def send_payload(self, msg_id: int, payload: bytes, crc_extra: int) -> None:
        """A MAVLink 2 frame built by hand, for fields pymavlink 2.4.50 leaves out."""
        assert self.dest is not None
        payload = payload.rstrip(b"\0") or b"\0"  # MAVLink 2 drops trailing zero bytes
        header = struct.pack("<BBBBBBB", len(payload), 0, 0, self.mav.seq, QGC_SYSID,
                             QGC_COMPID, msg_id & 0xFF) + struct.pack("<H", msg_id >> 8)
        crc = mavlink.x25crc(header + payload)
        crc.accumulate([crc_extra])
        self.sock.sendto(b"\xfd" + header + payload + struct.pack("<H", crc.crc), self.dest)
        self.mav.seq = (self.mav.seq + 1) & 0xFF


class Replay:
    """One QGC session with one vehicle: the vehicle's first HEARTBEAT has been heard."""

    def __init__(self, vehicle: SyntheticVehicle, link: QgcLink, heartbeat: Any) -> None:
        self.vehicle = vehicle
        self.link = link
        self.heartbeat = heartbeat
        self.sysid = heartbeat.get_srcSystem()

    def from_autopilot(self, msg: Any) -> bool:
        _msg_id, system, component = header_of(msg)
        return system == self.sysid and component == AUTOPILOT_COMP

    def command(self, cmd: int, *params: float) -> tuple[int, Any]:
        """COMMAND_LONG as Vehicle::_sendMavCommandFromList builds it (unused params 0,
        confirmation 0); returns (mark before sending, the COMMAND_ACK QGC matches or None)."""
        p = list(params) + [0.0] * (7 - len(params))
        mark = self.link.mark()
        self.link.send(mavlink.MAVLink_command_long_message(self.sysid, AUTOPILOT_COMP, cmd, 0,
                                                            *p))
        # Vehicle::_handleCommandAck matches the sender's component and the command number
        ack = self.link.wait(mark, ACK_TIMEOUT_S, lambda m: m.get_type() == "COMMAND_ACK"
                             and m.command == cmd and self.from_autopilot(m))
        return mark, ack

    def request_message(self, msg_id: int, param2: float = 0.0) -> tuple[Any, Any]:
        """Vehicle::requestMessage: returns (COMMAND_ACK, the requested message or None).

        The message may come before the ACK; after an ACCEPTED ACK QGC waits 1 s for it."""
        mark, ack = self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, msg_id, param2)
        assert ack is not None, f"no COMMAND_ACK for REQUEST_MESSAGE({msg_id}) within {ACK_TIMEOUT_S} s"
        if ack.result != mavlink.MAV_RESULT_ACCEPTED:
            return ack, None
        msg = self.link.wait(mark, MESSAGE_AFTER_ACK_S,
                             lambda m: header_of(m)[0] == msg_id and self.from_autopilot(m))
        return ack, msg


def header_of(msg: Any) -> tuple[int, int, int]:
    """(message id, system, component): pymavlink's placeholder for an id it does not know
    reports none of them, so they are read from the frame."""
    if msg.get_msgId() >= 0:
        return msg.get_msgId(), msg.get_srcSystem(), msg.get_srcComponent()
    buf = bytes(msg.get_msgbuf())
    return int.from_bytes(buf[7:10], "little"), buf[5], buf[6]


def raw_fields(msg: Any, msg_id: int) -> tuple[Any, ...]:
    """Fields of a message pymavlink 2.4.50 may not know, from its frame, with its CRC checked."""
    layout, crc_extra = RAW_LAYOUTS[msg_id]
    buf = bytes(msg.get_msgbuf())
    assert buf[0] == 0xFD, "not a MAVLink 2 frame"
    length = buf[1]
    assert int.from_bytes(buf[7:10], "little") == msg_id
    crc = mavlink.x25crc(buf[1:10 + length])
    crc.accumulate([crc_extra])
    assert struct.unpack("<H", buf[10 + length:12 + length])[0] == crc.crc, \
        f"message {msg_id}: CRC does not match CRC_EXTRA {crc_extra}: QGC would drop it"
    size = struct.calcsize(layout)
    return struct.unpack(layout, buf[10:10 + length].ljust(size, b"\0")[:size])


def c_string(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("utf-8", errors="replace")


def heartbeat_qgc() -> Any:
    """MultiVehicleManager::_sendGCSHeartbeat."""
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                             mavlink.MAV_MODE_MANUAL_ARMED, 0,
                                             mavlink.MAV_STATE_ACTIVE, 3)


@contextmanager
def session(**kwargs: Any) -> Iterator[Replay]:
    """A vehicle streaming to QGC's port, and QGC having heard its first HEARTBEAT."""
    link = QgcLink()
    try:
        with SyntheticVehicle([f"udpout:127.0.0.1:{link.port}"], extra_params=EXTRA,
                              **kwargs) as v:
            hb = link.wait(0, HEARTBEAT_LOST_S, lambda m: m.get_type() == "HEARTBEAT")
            assert hb is not None, "no HEARTBEAT: QGC would never create the vehicle"
            link.send(heartbeat_qgc())  # MultiVehicleManager sends one at once, then 1 Hz
            yield Replay(v, link, hb)
    finally:
        link.close()


@pytest.fixture
def qgc() -> Iterator[Replay]:
    with session() as replay:
        yield replay


# --------------------------------------------------------------------- MAVLink FTP as QGC drives it
class FtpError(AssertionError):
    pass


class QgcFtp:
    """FTPManager's download, step for step: OpenFileRO, BurstReadFile, ReadFile for holes,
    ResetSessions; sequence numbers as `_sendRequestExpectAck` sets them."""

    def __init__(self, replay: Replay, comp: int) -> None:
        self.replay = replay
        self.comp = comp
        self.expected = 0  # FTPManager::_expectedIncomingSeqNumber starts at 0

    def _is_reply(self, m: Any) -> bool:
        # FTPManager::_mavlinkMessageReceived: from the vehicle's system and the FTP component,
        # addressed to QGC's system
        return (m.get_type() == "FILE_TRANSFER_PROTOCOL" and m.get_srcSystem() == self.replay.sysid
                and m.get_srcComponent() == self.comp and m.target_system == QGC_SYSID)

    def send(self, opcode: int, *, session: int = 0, size: int = 0, offset: int = 0,
             data: bytes = b"", retry: bool = False) -> int:
        if retry:
            self.expected -= 2  # a retry repeats the previous sequence number
        seq = (self.expected + 1) & 0xFFFF
        self.expected = (self.expected + 2) & 0xFFFF
        payload = FTP_HEADER.pack(seq, session, opcode, size, 0, 0, 0, offset) + data
        mark = self.replay.link.mark()
        self.replay.link.send(mavlink.MAVLink_file_transfer_protocol_message(
            0, self.replay.sysid, self.comp, list(payload.ljust(251, b"\0")[:251])))
        return mark

    def reply(self, mark: int, req_opcode: int, *, exact_seq: bool = True) -> tuple[Any, bytes]:
        def match(m: Any) -> bool:
            if not self._is_reply(m):
                return False
            hdr = FTP_HEADER.unpack(bytes(m.payload[:FTP_HEADER.size]))
            if hdr[4] != req_opcode:
                return False
            return hdr[0] == self.expected if exact_seq else _seq_not_older(hdr[0], self.expected)
        m = self.replay.link.wait(mark, FTP_REPLY_S, match)
        if m is None:
            raise FtpError(f"no FTP reply to opcode {req_opcode} with seq {self.expected} "
                           f"within {FTP_REPLY_S} s")
        raw = bytes(m.payload)
        return FTP_HEADER.unpack(raw[:FTP_HEADER.size]), raw[FTP_HEADER.size:]

    def download(self, path: str) -> bytes:
        name = path.encode()[:FTP_DATA_LEN]
        hdr, data = self.reply(self.send(FTP_OPEN_RO, size=len(name), data=name), FTP_OPEN_RO)
        if hdr[2] != FTP_ACK:
            raise FtpError(f"OpenFileRO {path!r} refused: error {data[0] if data else None}")
        if hdr[3] != 4:  # FTPManager::_openFileROAckOrNak
            raise FtpError(f"OpenFileRO ACK carries {hdr[3]} bytes, QGC wants the 4-byte length")
        session, length = hdr[1], struct.unpack("<I", data[:4])[0]
        content = bytearray(length)
        have = [False] * length
        offset = 0
        missing: list[tuple[int, int]] = []
        mark = self.send(FTP_BURST, session=session, size=FTP_DATA_LEN, offset=0)
        deadline = time.monotonic() + 5.0 + length / 2000.0  # bounds a misbehaving server
        while True:
            if time.monotonic() > deadline:
                raise FtpError("burst read does not end")
            # within a burst every packet restarts QGC's 1 s timer; stale sequence numbers are
            # ignored (FTPManager::_burstReadFileAckOrNak)
            hdr, data = self.reply(mark, FTP_BURST, exact_seq=False)
            mark = self.replay.link.after
            seq, sess, opcode, size, _req, burst_done, _pad, ofs = hdr
            if opcode == FTP_NAK:
                if data[0] != FTP_ERR_EOF:
                    raise FtpError(f"burst read NAK error {data[0]}")
                if seq != self.expected:  # EOF out of order: QGC asks again from where it is
                    self.expected = seq
                    mark = self.send(FTP_BURST, session=session, size=FTP_DATA_LEN, offset=offset)
                    continue
                break
            if sess != session:
                raise FtpError("burst data for another session")
            if ofs > offset:
                missing.append((offset, ofs - offset))
            elif ofs < offset:
                continue
            if ofs + size > length:
                raise FtpError(f"data past the announced length {length}")
            content[ofs:ofs + size] = data[:size]
            have[ofs:ofs + size] = [True] * size
            offset = ofs + size
            if burst_done:
                self.expected = seq
                mark = self.send(FTP_BURST, session=session, size=FTP_DATA_LEN, offset=offset)
            else:
                self.expected = (seq + 1) & 0xFFFF
        for start, count in missing:  # FTPManager::_fillMissingBlocksWorker
            while count > 0:
                want = min(count, FTP_DATA_LEN)
                hdr, data = self.reply(self.send(FTP_READ, session=session, size=want,
                                                 offset=start), FTP_READ)
                if hdr[2] != FTP_ACK or hdr[7] != start or hdr[3] == 0:
                    raise FtpError(f"ReadFile at {start} failed")
                content[start:start + hdr[3]] = data[:hdr[3]]
                have[start:start + hdr[3]] = [True] * hdr[3]
                start, count = start + hdr[3], count - hdr[3]
        if not all(have):  # QGC compares the bytes written with the announced length
            raise FtpError(f"{have.count(False)} of {length} bytes never arrived")
        hdr, _ = self.reply(self.send(FTP_RESET), FTP_RESET)
        if hdr[2] != FTP_ACK:
            raise FtpError("ResetSessions not ACKed")
        return bytes(content)


def _seq_not_older(seq: int, expected: int) -> bool:
    return ((seq - expected) & 0xFFFF) < 0x8000


def qgc_ftp_path(uri: str) -> tuple[str, int]:
    """FTPManager::_parseURI: the path QGC opens and the component it asks."""
    path, comp = uri, AUTOPILOT_COMP
    if path.lower().startswith("mftp://"):
        path = path[len("mftp://") - 1:]  # one "/" is kept
    assert "://" not in path, f"QGC refuses {uri!r}"
    m = re.match(r"^/?\[;comp=(\d+)\]", path)
    if m:
        comp = int(m.group(1))
        path = re.sub(r"\[;comp=\d+\]", "", path)
    return path, comp


def inflate(path: str, data: bytes) -> bytes:
    """QGCCompression::decompressIfNeeded: by extension, else by the first bytes."""
    lower = path.lower()
    if lower.endswith((".xz", ".lzma")) or data.startswith(b"\xfd7zXZ\x00"):
        return lzma.decompress(data)
    if lower.endswith(".gz") or data.startswith(b"\x1f\x8b"):
        return gzip.decompress(data)
    return data


def crc_identifies(crc: int, served: bytes, content: bytes) -> bool:
    """QGC caches a metadata file under its announced CRC and reuses the cached copy whenever
    the CRC is the same, so the CRC must follow the file. Accepted: the CRC32 of the bytes
    served (or of their decompressed content), as zlib computes it or in MAVLink's variant
    (initial value 0, no final XOR: PX4's and MAVLink FTP's CalcFileCRC32)."""
    def variants(data: bytes) -> set[int]:
        return {zlib.crc32(data) & 0xFFFFFFFF,
                (zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF) & 0xFFFFFFFF}
    return crc in variants(served) | variants(content)


def fetch_general_metadata(replay: Replay) -> tuple[dict[str, Any], str]:
    """Steps #6 and #8: COMPONENT_METADATA, then the general file over MAVLink FTP."""
    ack, msg = replay.request_message(MSG_COMPONENT_METADATA)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED, \
        f"COMPONENT_METADATA refused ({ack.result}): QGC falls back to COMPONENT_INFORMATION"
    assert msg is not None, f"COMPONENT_METADATA not sent within {MESSAGE_AFTER_ACK_S} s of the ACK"
    _t, file_crc, uri_raw = raw_fields(msg, MSG_COMPONENT_METADATA)
    assert b"\0" in uri_raw, "the uri must be zero terminated (at most 99 characters)"
    uri = c_string(uri_raw)
    assert uri.lower().startswith("mftp://"), f"general metadata uri {uri!r} is not mftp"
    path, comp = qgc_ftp_path(uri)
    served = QgcFtp(replay, comp).download(path)
    content = inflate(path, served)
    assert crc_identifies(file_crc, served, content), \
        f"file_crc {file_crc:#010x} is not the CRC32 of the file: QGC would cache stale metadata"
    return json.loads(content), uri


def check_general_json(doc: dict[str, Any]) -> dict[int, dict[str, Any]]:
    """CompInfoGeneral::setJson; returns the usable entries by COMP_METADATA_TYPE."""
    assert isinstance(doc, dict)
    assert isinstance(doc.get("version"), (int, float)) and doc["version"] == 1
    assert isinstance(doc.get("metadataTypes"), list)
    usable = {}
    for entry in doc["metadataTypes"]:
        kind = entry.get("type", -1) if isinstance(entry, dict) else -1
        if not isinstance(kind, int) or kind < 0:
            continue
        # QGC skips an entry without a uri or without a fileCrc
        assert isinstance(entry.get("uri"), str) and entry["uri"], f"type {kind}: no uri"
        assert "fileCrc" in entry and isinstance(entry["fileCrc"], int) \
            and 0 <= entry["fileCrc"] <= 0xFFFFFFFF, f"type {kind}: fileCrc missing or not a uint32"
        usable[kind] = entry
    return usable


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


# ===================================================================== the sequence, in QGC's order
def test_0_first_heartbeat_makes_qgc_create_a_generic_fixed_wing(qgc: Replay) -> None:
    """MultiVehicleManager::_vehicleHeartbeatInfo and FirmwarePluginManager: component 1, a
    vehicle type, a non-zero system id other than QGC's; the autopilot picks the plugin."""
    hb = qgc.heartbeat
    assert qgc.from_autopilot(hb)
    assert hb.type not in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                           mavlink.MAV_TYPE_GIMBAL, mavlink.MAV_TYPE_ADSB)
    assert hb.type == mavlink.MAV_TYPE_FIXED_WING
    assert qgc.sysid not in (0, QGC_SYSID)
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_GENERIC  # QGC's generic plugin
    # the generic plugin names the mode from the base-mode flags unless the custom flag is set
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    # VehicleLinkManager: no HEARTBEAT for 3.5 s means the link is lost
    mark = qgc.link.mark()
    nxt = qgc.link.wait(mark, HEARTBEAT_LOST_S,
                        lambda m: m.get_type() == "HEARTBEAT" and qgc.from_autopilot(m))
    assert nxt is not None


def test_1_autopilot_version(qgc: Replay) -> None:
    """InitialConnectStateMachine::_stateRequestAutopilotVersion."""
    ack, msg = qgc.request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert msg is not None, f"AUTOPILOT_VERSION not sent within {MESSAGE_AFTER_ACK_S} s of the ACK"
    assert msg.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    # QGC splits flight_sw_version into 4 bytes: major, minor, patch, FIRMWARE_VERSION_TYPE;
    # they must spell the package's version, not merely fit in a byte each
    word = msg.flight_sw_version
    shown = ((word >> 24) & 0xFF, (word >> 16) & 0xFF, (word >> 8) & 0xFF)
    release = re.match(r"(\d+)\.(\d+)\.(\d+)", __version__)
    assert release is not None, __version__
    assert shown == tuple(int(p) for p in release.groups()), (hex(word), __version__)
    assert word & 0xFF == mavlink.FIRMWARE_VERSION_TYPE_DEV, hex(word)


def test_2_protocol_version_for_qgc_5(qgc: Replay) -> None:
    """QGC 5.x: _stateRequestProtocolVersion; without an answer QGC falls back to MAVLink 1."""
    ack, msg = qgc.request_message(MSG_PROTOCOL_VERSION)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert msg is not None, "PROTOCOL_VERSION not sent: QGC 5.x would drop to MAVLink 1"
    _version, _min, max_version, _spec, _lib = raw_fields(msg, MSG_PROTOCOL_VERSION)
    assert max_version >= 200


def test_3_camera_probe_is_refused_at_once(qgc: Replay) -> None:
    """QGCCameraManager probes component 1 on its first HEARTBEAT, alternating the two forms;
    an immediate refusal keeps it from holding REQUEST_MESSAGE while the sequence runs."""
    # docs/qgc-connection.md #4: UNSUPPORTED at once, both forms (ACCEPTED would make QGC wait
    # for CAMERA_INFORMATION and retry for about 30 s)
    _mark, ack = qgc.command(CMD_REQUEST_CAMERA_INFORMATION, 1)
    assert ack is not None, "MAV_CMD_REQUEST_CAMERA_INFORMATION not acknowledged"
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    ack, msg = qgc.request_message(MSG_CAMERA_INFORMATION)
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    assert msg is None


def test_4_available_modes_step_ends_in_one_round_trip_or_a_complete_walk(qgc: Replay) -> None:
    """StandardModes::requestMode: index 1, 2, ... until mode_index >= number_modes; any
    refusal ends the step. Refusing with UNSUPPORTED is the fastest (see the page)."""
    ack, msg = qgc.request_message(MSG_AVAILABLE_MODES, 1)
    if ack.result != mavlink.MAV_RESULT_ACCEPTED:
        assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    else:
        index = 1
        while True:
            assert msg is not None, f"AVAILABLE_MODES index {index} not sent"
            _custom, _props, number, mode_index, standard, name = raw_fields(msg, MSG_AVAILABLE_MODES)
            assert mode_index == index and number >= 1
            assert standard != 0 or c_string(name), "a mode needs a name or a standard mode"
            if mode_index >= number:
                break
            index += 1
            assert index <= 64, "the walk does not end"
            ack, msg = qgc.request_message(MSG_AVAILABLE_MODES, index)
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    # newer QGC (StandardModes 117ed905) asks for all modes at once with param2 = 0
    mark, ack = qgc.command(mavlink.MAV_CMD_REQUEST_MESSAGE, MSG_AVAILABLE_MODES, 0)
    assert ack is not None
    if ack.result != mavlink.MAV_RESULT_ACCEPTED:
        assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
        return
    indices: set[int] = set()
    total: int | None = None
    while total is None or len(indices) < total:
        msg = qgc.link.wait(mark, MESSAGE_AFTER_ACK_S,
                            lambda m: header_of(m)[0] == MSG_AVAILABLE_MODES
                            and qgc.from_autopilot(m))
        assert msg is not None, f"all modes asked, {len(indices)} of {total} sent"
        mark = qgc.link.after
        fields = raw_fields(msg, MSG_AVAILABLE_MODES)
        total = fields[2] if total is None else total
        assert fields[2] == total and 1 <= fields[3] <= total
        indices.add(fields[3])


def test_5_component_metadata_step_ends_within_qgc_timeouts(qgc: Replay) -> None:
    """RequestMetaDataTypeStateMachine: COMPONENT_METADATA, and COMPONENT_INFORMATION only when
    that failed; a refusal of both means no metadata and no delay."""
    ack, msg = qgc.request_message(MSG_COMPONENT_METADATA)
    if ack.result == mavlink.MAV_RESULT_ACCEPTED:
        assert msg is not None, "COMPONENT_METADATA ACCEPTED but not sent"
        raw_fields(msg, MSG_COMPONENT_METADATA)
        return
    ack, msg = qgc.request_message(MSG_COMPONENT_INFORMATION)
    if ack.result == mavlink.MAV_RESULT_ACCEPTED:
        assert msg is not None, "COMPONENT_INFORMATION ACCEPTED but not sent"
        raw_fields(msg, MSG_COMPONENT_INFORMATION)


def test_6_component_metadata_general_file_over_mftp(qgc: Replay) -> None:
    """COMPONENT_METADATA, then FTPManager::download of the general file, then
    CompInfoGeneral::setJson; a parameter metadata entry (type 1) must be usable."""
    doc, _uri = fetch_general_metadata(qgc)
    usable = check_general_json(doc)
    assert METADATA_PARAMETER in usable, "no usable parameter metadata entry (uri and fileCrc)"
    for entry in usable.values():
        if entry["uri"].lower().startswith("mftp://"):
            qgc_ftp_path(entry["uri"])  # a uri QGC can parse


def test_7_parameter_metadata_json_matches_the_parameters(qgc: Replay) -> None:
    """CompInfoParam::setJson and FactMetaData::createFromJsonObject: version 1, a parameters
    array, and for each parameter the keys QGC validates with the JSON types it requires (one
    wrong type and QGC drops that parameter's metadata)."""
    doc, _uri = fetch_general_metadata(qgc)
    entry = check_general_json(doc)[METADATA_PARAMETER]
    path, comp = qgc_ftp_path(entry["uri"])
    served = QgcFtp(qgc, comp).download(path)
    content = inflate(path, served)
    assert crc_identifies(entry["fileCrc"], served, content)
    meta = json.loads(content)
    assert meta.get("version") == 1 and isinstance(meta.get("parameters"), list)
    by_name: dict[str, dict[str, Any]] = {}
    for p in meta["parameters"]:
        assert isinstance(p, dict), "a non-object element stops QGC reading the rest"
        for key in STRING_KEYS:
            assert key not in p or isinstance(p[key], str), f"{p.get('name')}: {key} not a string"
        for key in NUMBER_KEYS:
            assert key not in p or is_number(p[key]), f"{p.get('name')}: {key} not a number"
        for key in BOOL_KEYS:
            assert key not in p or isinstance(p[key], bool), f"{p.get('name')}: {key} not a bool"
        for key in ARRAY_KEYS:
            assert key not in p or isinstance(p[key], list), f"{p.get('name')}: {key} not an array"
        assert isinstance(p.get("name"), str) and p["name"], "name is required"
        assert isinstance(p.get("type"), str) and p["type"].lower() in QGC_TYPES, \
            f"{p['name']}: unknown type {p.get('type')!r}"
        if p["type"].lower() not in ("string", "custom"):
            for key in ("default", "increment"):
                assert key not in p or is_number(p[key]), f"{p['name']}: {key} not a number"
        by_name[p["name"]] = p
    values = list_parameters(qgc)
    for name, (ptype, _raw) in values.items():
        assert name in by_name, f"{name} has no metadata"
        assert by_name[name]["type"].lower() == QGC_TYPE_OF_PARAM[ptype], \
            f"{name}: metadata type {by_name[name]['type']} but PARAM_VALUE type {ptype}"


def list_parameters(qgc: Replay) -> dict[str, tuple[int, float]]:
    """ParameterManager::refreshAllParameters and _handleParamValue, within QGC's timers:
    returns name -> (param_type, param_value) for component 1."""
    mark = qgc.link.mark()
    qgc.link.send(mavlink.MAVLink_param_request_list_message(qgc.sysid, 0))  # component: all
    values: dict[str, tuple[int, float]] = {}
    indices: set[int] = set()
    count: int | None = None
    timeout = PARAM_FIRST_S
    while count is None or len(indices) < count:
        m = qgc.link.wait(mark, timeout, lambda m: m.get_type() == "PARAM_VALUE")
        assert m is not None, (f"PARAM_VALUE {len(indices)} of {count} not within {timeout} s: "
                               "QGC would re-request by index")
        mark = qgc.link.after
        timeout = PARAM_GAP_S
        assert qgc.from_autopilot(m), "parameters must come from component 1 (the HEARTBEAT's)"
        if count is None:
            count = m.param_count
        assert m.param_count == count
        assert m.param_index != 65535 and 0 <= m.param_index < count
        indices.add(m.param_index)
        values[m.param_id] = (m.param_type, m.param_value)
    return values


def test_8_parameter_list_complete_and_bytewise(qgc: Replay) -> None:
    """The whole list within QGC's timers, from component 1; QGC decodes integers bytewise
    (ParameterManager::_mavlinkParamUnionToVariant) for every non-ArduPilot component."""
    values = list_parameters(qgc)
    assert set(values) == {s.name for s in qgc.vehicle.params.specs()}
    for name, (ptype, value) in values.items():
        assert ptype in QGC_TYPE_OF_PARAM, f"{name}: QGC cannot decode type {ptype}"
        raw = struct.pack("<f", value)
        if ptype == mavlink.MAV_PARAM_TYPE_INT32:
            assert struct.unpack("<i", raw)[0] == qgc.vehicle.params.get(name), name
        elif ptype == mavlink.MAV_PARAM_TYPE_REAL32:
            want = struct.unpack("<f", struct.pack("<f", float(qgc.vehicle.params.get(name))))[0]
            assert value == want or (math.isnan(value) and math.isnan(want)), name
    assert struct.unpack("<i", struct.pack("<f", values["TST_BIG"][1]))[0] == BIG
    # Vehicle::_parametersReady: SYSTEM_TIME twice; the vehicle carries on
    now_us = int(time.time() * 1e6)
    for _ in range(2):
        qgc.link.send(mavlink.MAVLink_system_time_message(now_us, 0))
    mark = qgc.link.mark()
    assert qgc.link.wait(mark, HEARTBEAT_LOST_S, lambda m: m.get_type() == "HEARTBEAT"
                         and qgc.from_autopilot(m)) is not None


def test_9_gimbal_probe_is_refused_at_once(qgc: Replay) -> None:
    """GimbalController::_requestGimbalInformation, after the parameters."""
    # docs/qgc-connection.md #12: UNSUPPORTED at once, and no message
    ack, msg = qgc.request_message(MSG_GIMBAL_MANAGER_INFORMATION)
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    assert msg is None


def mission_reply(mission_type: int) -> Callable[[Any], bool]:
    return lambda m: (m.get_type() in ("MISSION_COUNT", "MISSION_ACK")
                      and m.mission_type == mission_type)


def mission_item(mission_type: int, seq: int) -> Callable[[Any], bool]:
    return lambda m: (m.get_type() == "MISSION_ITEM_INT" and m.seq == seq
                      and m.mission_type == mission_type)


def test_10_mission_fence_rally(qgc: Replay) -> None:
    """PlanManager::_requestList per mission type; fence and rally only with the capability
    bits of AUTOPILOT_VERSION (GeoFenceManager / RallyPointManager::supported)."""
    _ack, version = qgc.request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert version is not None
    types = [mavlink.MAV_MISSION_TYPE_MISSION]
    if version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE:
        types.append(mavlink.MAV_MISSION_TYPE_FENCE)
    if version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY:
        types.append(mavlink.MAV_MISSION_TYPE_RALLY)
    for mission_type in types:
        mark = qgc.link.mark()
        qgc.link.send(mavlink.MAVLink_mission_request_list_message(qgc.sysid, AUTOPILOT_COMP,
                                                                   mission_type))
        reply = qgc.link.wait(mark, MISSION_COUNT_S, mission_reply(mission_type))
        assert reply is not None, f"no MISSION_COUNT for type {mission_type} within {MISSION_COUNT_S} s"
        assert reply.get_type() == "MISSION_COUNT", \
            f"MISSION_ACK {reply.type} instead of MISSION_COUNT: QGC shows 'Mission transfer failed'"
        for seq in range(reply.count):
            mark = qgc.link.mark()
            qgc.link.send(mavlink.MAVLink_mission_request_int_message(
                qgc.sysid, AUTOPILOT_COMP, seq, mission_type))
            item = qgc.link.wait(mark, MISSION_ITEM_S, mission_item(mission_type, seq))
            assert item is not None, f"item {seq} of type {mission_type} not sent"
        # PlanManager::_readTransactionComplete
        qgc.link.send(mavlink.MAVLink_mission_ack_message(qgc.sysid, AUTOPILOT_COMP,
                                                          mavlink.MAV_MISSION_ACCEPTED, mission_type))


def test_11_fly_view_needs_no_request(qgc: Replay) -> None:
    """The generic plugin asks for no stream: what the Fly view shows must be sent by default
    (Vehicle::_mavlinkMessageReceived and the fact groups)."""
    got = qgc.link.gather(2.5)
    by_type: dict[str, list[tuple[float, Any]]] = {}
    for t, m in got:
        if qgc.from_autopilot(m):
            by_type.setdefault(m.get_type(), []).append((t, m))
    beats = [t for t, _m in by_type.get("HEARTBEAT", [])]
    assert len(beats) >= 2
    assert max(b - a for a, b in zip(beats, beats[1:], strict=False)) < HEARTBEAT_LOST_S
    assert "ATTITUDE_QUATERNION" in by_type or "ATTITUDE" in by_type
    assert any(m.lat != 0 or m.lon != 0 for _t, m in by_type.get("GLOBAL_POSITION_INT", [])), \
        "no map position (GLOBAL_POSITION_INT with a non-zero lat/lon)"
    for name in ("VFR_HUD", "GPS_RAW_INT", "SYS_STATUS", "BATTERY_STATUS"):
        assert name in by_type, f"{name} is not streamed: QGC never asks for it"
    # QGC never asks for HOME_POSITION either; this link heard it when the origin appeared
    assert any(m.get_type() == "HOME_POSITION" and qgc.from_autopilot(m)
               for _t, m in qgc.link.inbox)


def test_12_landed_state_from_extended_sys_state(qgc: Replay) -> None:
    """Vehicle::_handleExtendedSysState: without it QGC never considers the aircraft flying
    (UNDEFINED, sent before the estimator has aligned, changes nothing in QGC)."""
    mark = qgc.link.mark()
    # the synthetic aircraft flies a 20 m/s circle
    m = qgc.link.wait(mark, 2.5, lambda m: m.get_type() == "EXTENDED_SYS_STATE"
                      and qgc.from_autopilot(m)
                      and m.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR)
    assert m is not None, "no EXTENDED_SYS_STATE saying IN_AIR: QGC shows the aircraft landed"


def test_13_ftp_refusal_and_reset_are_answered_in_sequence(qgc: Replay) -> None:
    """FTPManager: a missing file is refused with a one-byte NAK (else 'Invalid Nak format'),
    ResetSessions (the end of every download) is ACKed; replies carry request seq + 1."""
    ftp = QgcFtp(qgc, AUTOPILOT_COMP)
    name = b"/qgc-replay/does-not-exist.json"
    hdr, data = ftp.reply(ftp.send(FTP_OPEN_RO, size=len(name), data=name), FTP_OPEN_RO)
    assert hdr[2] == FTP_NAK
    assert hdr[3] == (2 if data[0] == FTP_ERR_FAIL_ERRNO else 1)
    hdr, _data = ftp.reply(ftp.send(FTP_RESET), FTP_RESET)
    assert hdr[2] == FTP_ACK


def test_14_onboard_logs_page(tmp_path: Path) -> None:
    """LogDownloadController: LOG_REQUEST_LIST 0..0xFFFF, entries with 0-based ids for a
    non-ArduPilot vehicle, then LOG_REQUEST_DATA per 46 080-byte chunk of 90-byte bins."""
    flight = tmp_path / "20260101T000000Z"  # a flight directory named as the runtime names them
    flight.mkdir()
    notes = bytes(range(256)) * 400  # more than two of QGC's chunks
    (flight / "notes.txt").write_bytes(notes)
    with session(flight_dir=flight) as qgc:
        log = _download_first_log(qgc)
    assert len(log) > 2 * 512 * 90
    # QGC saves the bytes as they came; the bridge serves a flight as a tar archive
    with tarfile.open(fileobj=io.BytesIO(log)) as tar:
        member = next(m for m in tar.getmembers() if m.name.endswith("notes.txt"))
        extracted = tar.extractfile(member)
        assert extracted is not None and extracted.read() == notes


def _download_first_log(qgc: Replay) -> bytes:
    """Lists the logs and downloads the smallest non-empty one (b"": none)."""
    mark = qgc.link.mark()
    qgc.link.send(mavlink.MAVLink_log_request_list_message(qgc.sysid, AUTOPILOT_COMP, 0, 0xFFFF))
    entries: dict[int, Any] = {}
    num_logs: int | None = None
    timeout = LOG_LIST_FIRST_S
    while num_logs is None or len(entries) < num_logs:
        m = qgc.link.wait(mark, timeout, lambda m: m.get_type() == "LOG_ENTRY")
        assert m is not None, f"LOG_ENTRY not within {timeout} s"
        mark = qgc.link.after
        timeout = LOG_NEXT_S
        if num_logs is None:
            num_logs = m.num_logs
        if num_logs == 0:
            return b""  # one entry with num_logs 0 ends the listing at once
        assert m.num_logs == num_logs and 0 <= m.id < num_logs, "ids are 0-based row numbers"
        entries[m.id] = m
    sized = [e for e in entries.values() if e.size > 0]
    if not sized:
        return b""
    entry = min(sized, key=lambda e: e.size)
    chunk_bytes = 512 * 90
    received = bytearray(entry.size)
    got = [False] * math.ceil(entry.size / 90)
    for chunk_start in range(0, entry.size, chunk_bytes):
        bins = min(512, math.ceil((entry.size - chunk_start) / 90))
        mark = qgc.link.mark()
        qgc.link.send(mavlink.MAVLink_log_request_data_message(qgc.sysid, AUTOPILOT_COMP,
                                                               entry.id, chunk_start, bins * 90))
        first_bin = chunk_start // 90
        while not all(got[first_bin:first_bin + bins]):
            d = qgc.link.wait(mark, LOG_NEXT_S, lambda m: m.get_type() == "LOG_DATA")
            assert d is not None, f"LOG_DATA stalled at chunk {chunk_start}"
            mark = qgc.link.after
            assert d.id == entry.id and d.ofs % 90 == 0 and d.count <= 90
            assert chunk_start <= d.ofs < chunk_start + chunk_bytes, "packet for another chunk"
            received[d.ofs:d.ofs + d.count] = bytes(d.data[:d.count])
            got[d.ofs // 90] = True
    return bytes(received)


def test_15_mavlink_console(qgc: Replay) -> None:
    """MAVLinkConsoleController::_sendSerialData: device SHELL, flags RESPOND | EXCLUSIVE |
    MULTI, 70-byte data, target fields; QGC shows only SERIAL_CONTROL with device SHELL."""
    line = b"help\n"
    flags = (mavlink.SERIAL_CONTROL_FLAG_EXCLUSIVE | mavlink.SERIAL_CONTROL_FLAG_RESPOND
             | mavlink.SERIAL_CONTROL_FLAG_MULTI)
    payload = struct.pack("<IHBBB70sBB", 0, 0, mavlink.SERIAL_CONTROL_DEV_SHELL, flags, len(line),
                          line.ljust(70, b"\0"), qgc.sysid, AUTOPILOT_COMP)
    mark = qgc.link.mark()
    qgc.link.send_payload(mavlink.MAVLINK_MSG_ID_SERIAL_CONTROL, payload,
                          mavlink.MAVLink_serial_control_message.crc_extra)
    reply = qgc.link.wait(mark, CONSOLE_REPLY_S, lambda m: m.get_type() == "SERIAL_CONTROL"
                          and qgc.from_autopilot(m))
    assert reply is not None, "the console says nothing (QGC never polls for output)"
    assert reply.device == mavlink.SERIAL_CONTROL_DEV_SHELL, "QGC ignores other devices"
    assert 0 < reply.count <= 70
