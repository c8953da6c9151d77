"""MAVLink FTP on the wire: the payload header, opcodes, error codes and payload builders.

What a FILE_TRANSFER_PROTOCOL payload means, independent of any file system or session: the
12-byte header (`HEADER`), the opcodes and NAK codes, parsing a request (`parse_request`), the
ACK/NAK payloads that answer it, request paths (`path_parts`), directory-listing entries and
MAVLink's CRC32. Separate from `ftp` (the server: sessions, confinement to the root, remembered
answers) so the format can be read, and tested, on its own.
"""

from __future__ import annotations

import os
import stat
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

from gcs_bridge.dialect import mavlink

HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst, pad, offset
PAYLOAD_LEN = 251
DATA_LEN = PAYLOAD_LEN - HEADER.size  # 239: the most data one payload carries
U32 = struct.Struct("<I")

OP_NONE = mavlink.MAV_FTP_OPCODE_NONE
OP_TERMINATE_SESSION = mavlink.MAV_FTP_OPCODE_TERMINATESESSION
OP_RESET_SESSIONS = mavlink.MAV_FTP_OPCODE_RESETSESSION
OP_LIST_DIRECTORY = mavlink.MAV_FTP_OPCODE_LISTDIRECTORY
OP_OPEN_FILE_RO = mavlink.MAV_FTP_OPCODE_OPENFILERO
OP_READ_FILE = mavlink.MAV_FTP_OPCODE_READFILE
OP_CREATE_FILE = mavlink.MAV_FTP_OPCODE_CREATEFILE
OP_WRITE_FILE = mavlink.MAV_FTP_OPCODE_WRITEFILE
OP_REMOVE_FILE = mavlink.MAV_FTP_OPCODE_REMOVEFILE
OP_CREATE_DIRECTORY = mavlink.MAV_FTP_OPCODE_CREATEDIRECTORY
OP_REMOVE_DIRECTORY = mavlink.MAV_FTP_OPCODE_REMOVEDIRECTORY
OP_OPEN_FILE_WO = mavlink.MAV_FTP_OPCODE_OPENFILEWO
OP_TRUNCATE_FILE = mavlink.MAV_FTP_OPCODE_TRUNCATEFILE
OP_RENAME = mavlink.MAV_FTP_OPCODE_RENAME
OP_CALC_FILE_CRC32 = mavlink.MAV_FTP_OPCODE_CALCFILECRC
OP_BURST_READ_FILE = mavlink.MAV_FTP_OPCODE_BURSTREADFILE
OP_LIST_DIRECTORY_WITH_TIME = 16  # in the FTP spec, newer than pymavlink's MAV_FTP_OPCODE
OP_ACK = mavlink.MAV_FTP_OPCODE_ACK
OP_NAK = mavlink.MAV_FTP_OPCODE_NAK

ERR_FAIL = mavlink.MAV_FTP_ERR_FAIL
ERR_FAILERRNO = mavlink.MAV_FTP_ERR_FAILERRNO
ERR_INVALIDDATASIZE = mavlink.MAV_FTP_ERR_INVALIDDATASIZE
ERR_INVALIDSESSION = mavlink.MAV_FTP_ERR_INVALIDSESSION
ERR_NOSESSIONSAVAILABLE = mavlink.MAV_FTP_ERR_NOSESSIONSAVAILABLE
ERR_EOF = mavlink.MAV_FTP_ERR_EOF
ERR_UNKNOWNCOMMAND = mavlink.MAV_FTP_ERR_UNKNOWNCOMMAND
ERR_FILEEXISTS = mavlink.MAV_FTP_ERR_FILEEXISTS
ERR_FILEPROTECTED = mavlink.MAV_FTP_ERR_FILEPROTECTED
ERR_FILENOTFOUND = mavlink.MAV_FTP_ERR_FILENOTFOUND

MAX_FILE_BYTES = 0xFFFFFFFF  # sizes and offsets are uint32 on the wire
_MASK32 = 0xFFFFFFFF


def mavlink_crc32(data: bytes, crc: int = 0) -> int:
    """MAVLink's CRC32 of `data`, continuing from `crc` (0 to start).

    MAVLink FTP uses the reflected CRC32 of 0x04C11DB7 started from 0 and without the final
    inversion (mavlink.io guide/crc, MAVSDK crc32.cpp, ArduPilot crc_crc32). zlib runs the same
    table but inverts on the way in and out, so handing it the inverted state cancels both.
    """
    return zlib.crc32(data, crc ^ _MASK32) ^ _MASK32


class Nak(Exception):
    """Ends a request with a NAK: `code` is a MAV_FTP_ERR, `errno_` is sent only with FAILERRNO."""

    def __init__(self, code: int, errno_: int = 0) -> None:
        super().__init__(code, errno_)
        self.code = code
        self.errno_ = errno_


def nak_for(exc: OSError) -> Nak:
    """The NAK for a file-system error: the two the spec names, else FAILERRNO with the errno
    (MAVSDK turns FAILERRNO+ENOENT into "does not exist" as well; ArduPilot maps the same two)."""
    if isinstance(exc, FileNotFoundError):
        return Nak(ERR_FILENOTFOUND)
    if isinstance(exc, FileExistsError):
        return Nak(ERR_FILEEXISTS)
    if exc.errno:
        return Nak(ERR_FAILERRNO, exc.errno & 0xFF)
    return Nak(ERR_FAIL)


@dataclass(frozen=True)
class Request:
    seq: int
    session: int
    opcode: int
    size: int
    offset: int
    data: bytes  # data[:size]

    @property
    def key(self) -> bytes:
        """What makes a request a re-send of another: all but the reply-only header fields."""
        head = struct.pack("<HBBBI", self.seq, self.session, self.opcode, self.size, self.offset)
        return head + self.data


def parse_request(payload: bytes) -> Request | None:
    """The request in a payload, None if too short to answer at all.

    MAVLink 2 trims trailing zeros off the wire, so a short payload is zero-padded, not refused.
    """
    if len(payload) < HEADER.size:
        return None
    body = payload[:PAYLOAD_LEN].ljust(PAYLOAD_LEN, b"\0")
    seq, session, opcode, size, _req, _burst, _pad, offset = HEADER.unpack_from(body)
    return Request(seq, session, opcode, size, offset, body[HEADER.size:HEADER.size + size])


def reply_payload(req: Request, opcode: int, data: bytes = b"", *, offset: int | None = None,
           seq_step: int = 1, burst_complete: bool = False) -> bytes:
    """A full reply payload: request seq + `seq_step`, the request's session and offset."""
    head = HEADER.pack((req.seq + seq_step) & 0xFFFF, req.session, opcode, len(data), req.opcode,
                       int(burst_complete), 0, req.offset if offset is None else offset)
    return (head + data).ljust(PAYLOAD_LEN, b"\0")


def nak_payload(req: Request, code: int, errno_: int = 0) -> bytes:
    """NAK: data[0] the error, data[1] the errno only with FAILERRNO (size 1 or 2)."""
    data = bytes([code, errno_]) if code == ERR_FAILERRNO else bytes([code])
    return reply_payload(req, OP_NAK, data, burst_complete=req.opcode == OP_BURST_READ_FILE)


def path_parts(raw: bytes) -> list[str]:
    """The components of a request path, which ends at its first NUL (MAVSDK counts the NUL in
    `size`, MAVProxy does not). "/x", "x" and "./x" are the same file under the root.

    ".." is refused outright rather than resolved: a path that climbs is never needed to name a
    file under the root, and refusing it keeps the check independent of what exists on disk.
    """
    text = os.fsdecode(raw.split(b"\0", 1)[0])
    parts = [part for part in text.split("/") if part not in ("", ".")]
    if ".." in parts:
        raise Nak(ERR_FILENOTFOUND)
    return parts


def path_key(parts: list[str]) -> str:
    return "/" + "/".join(parts)


def chunk_len(size: int) -> int:
    """Bytes to read for a ReadFile/BurstReadFile `size`: 0 means as many as fit (ArduPilot)."""
    return size if 0 < size <= DATA_LEN else DATA_LEN


def dir_entry(root: Path, directory: Path, name: str, with_time: bool) -> bytes:
    """"F<name>\\t<size>\\0" or "D<name>\\0" (with "\\t<mtime s>" appended, and "\\t0" as a
    directory's size, in the timed listing). An entry that cannot be shown (a tab in its name,
    too long for a payload, not a file or directory, leading out of the root, gone) is "S":
    skipped, but still counted, so the clients' offsets keep matching the server's indexes."""
    raw = os.fsencode(name)
    path = directory / name
    try:
        if b"\t" in raw or not path.resolve().is_relative_to(root):
            return b"S\0"
        info = os.stat(path)
    except (OSError, RuntimeError):
        return b"S\0"
    mtime = b"\t%d" % max(0, int(info.st_mtime)) if with_time else b""
    if stat.S_ISDIR(info.st_mode):
        entry = b"D" + raw + (b"\t0" + mtime if with_time else b"") + b"\0"
    elif stat.S_ISREG(info.st_mode):
        entry = b"F" + raw + b"\t%d" % info.st_size + mtime + b"\0"
    else:
        return b"S\0"
    return entry if len(entry) <= DATA_LEN else b"S\0"
