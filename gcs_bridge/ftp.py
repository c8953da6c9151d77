"""MAVLink FTP: the bridge has no file service, and says so at once.

MAVProxy (and QGroundControl for some metadata) first try to fetch parameters over MAVLink FTP;
a vehicle that stays silent costs them about 11 s before they fall back to the parameter
protocol, one that refuses costs about 1 s. Every request is therefore answered with a NAK
(sessions "closed" are ACKed, which is true of a server that has none).
"""

from __future__ import annotations

import struct

from gcs_bridge.dialect import mavlink

HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst, pad, offset
PAYLOAD_LEN = 251

OP_TERMINATE_SESSION = 1
OP_RESET_SESSIONS = 2
OP_OPEN_FILE_RO = 4
OP_OPEN_FILE_WO = 11
OP_CREATE_FILE = 6
OP_LIST_DIRECTORY = 3
OP_ACK = 128
OP_NAK = 129

_NOT_FOUND_OPS = {OP_OPEN_FILE_RO, OP_LIST_DIRECTORY, OP_OPEN_FILE_WO, OP_CREATE_FILE}


def reply_to(msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message | None:
    """The answer to a FILE_TRANSFER_PROTOCOL request, None for a malformed one."""
    payload = bytes(msg.payload)
    if len(payload) < HEADER.size:
        return None
    seq, session, opcode, _size, _req, _burst, _pad, _offset = HEADER.unpack(payload[:HEADER.size])
    if opcode in (OP_ACK, OP_NAK):  # a reply, not a request: never answer it
        return None
    if opcode in (OP_TERMINATE_SESSION, OP_RESET_SESSIONS):
        body = HEADER.pack((seq + 1) & 0xFFFF, session, OP_ACK, 0, opcode, 0, 0, 0)
    else:
        error = (mavlink.MAV_FTP_ERR_FILENOTFOUND if opcode in _NOT_FOUND_OPS
                 else mavlink.MAV_FTP_ERR_UNKNOWNCOMMAND)
        body = HEADER.pack((seq + 1) & 0xFFFF, session, OP_NAK, 1, opcode, 0, 0, 0) + bytes([error])
    data = list(body.ljust(PAYLOAD_LEN, b"\0"))
    return mavlink.MAVLink_file_transfer_protocol_message(
        0, msg.get_srcSystem(), msg.get_srcComponent(), data)
