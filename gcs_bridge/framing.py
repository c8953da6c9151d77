"""MAVLink frames cut from a byte stream, by their headers, resynchronising after damage.

pymavlink's parser, after a frame whose checksum fails, skips the whole length that the bad
header claimed. A header read at the wrong place claims a wrong length, so the parser lands at
the wrong place again; on a stream of similar frames (an autopilot's IMU at 50 Hz) it can stay
out of step for good. This splitter never trusts a header that its checksum did not confirm:
a frame that fails gives up one byte, and the search for the next start byte begins there.

It reads only the header (version, length, flags, ids) and checks the CRC with the message's
CRC_EXTRA from the dialect; a frame of a message the dialect does not know cannot be checked,
and is passed on as `known = False` (a router forwards it, a decoder skips it). The bytes of
every frame are handed out exactly as they came, signature included.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as apm
from pymavlink.generator.mavcrc import x25crc

__all__ = ["Frame", "FrameSplitter"]

STX_V1 = 0xFE
STX_V2 = 0xFD
SIGNATURE_LEN = 13
MAX_BUFFER = 1 << 16
_CRC_EXTRA: dict[int, int] = {mid: cls.crc_extra for mid, cls in apm.mavlink_map.items()}


@dataclass(frozen=True)
class Frame:
    """One whole frame: its bytes as received and what its header says."""

    data: bytes
    msg_id: int
    src_system: int
    src_component: int
    version: int
    known: bool
    """The dialect knows the message, so its CRC was checked."""


class FrameSplitter:
    """Feed bytes, get whole frames; keeps a partial frame between calls."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_crc = 0
        self.bytes_skipped = 0

    def reset(self) -> None:
        self._buf.clear()

    @property
    def pending(self) -> int:
        """Bytes held back: the start of a frame not yet whole."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        buf = self._buf
        buf += data
        out: list[Frame] = []
        pos = 0
        n = len(buf)
        while pos < n:
            start = _next_stx(buf, pos)
            if start < 0:
                self.bytes_skipped += n - pos
                pos = n
                break
            self.bytes_skipped += start - pos
            pos = start
            frame_len = _frame_length(buf, pos, n)
            if frame_len is None or pos + frame_len > n:
                break  # wait for the rest of the header or the frame
            frame = _check(buf, pos, frame_len)
            if frame is None:
                self.bad_crc += 1
                self.bytes_skipped += 1
                pos += 1  # give up the start byte only: the next frame may begin inside
                continue
            out.append(frame)
            pos += frame_len
        del buf[:pos]
        if len(buf) > MAX_BUFFER:  # nothing whole in 64 KiB: drop it rather than grow
            self.bytes_skipped += len(buf)
            buf.clear()
        return out


def _next_stx(buf: bytearray, pos: int) -> int:
    a = buf.find(STX_V2, pos)
    b = buf.find(STX_V1, pos)
    if a < 0:
        return b
    if b < 0:
        return a
    return min(a, b)


def _frame_length(buf: bytearray, pos: int, n: int) -> int | None:
    if buf[pos] == STX_V2:
        if pos + 3 > n:
            return None
        length = 10 + buf[pos + 1] + 2
        if buf[pos + 2] & 0x01:
            length += SIGNATURE_LEN
        return length
    if pos + 2 > n:
        return None
    return 6 + buf[pos + 1] + 2


def _check(buf: bytearray, pos: int, frame_len: int) -> Frame | None:
    v2 = buf[pos] == STX_V2
    payload_len = buf[pos + 1]
    if v2:
        if buf[pos + 2] & ~0x01:
            return None  # an incompatibility flag this protocol version does not define
        header = 10
        sys_at = pos + 5
        msg_id = buf[pos + 7] | buf[pos + 8] << 8 | buf[pos + 9] << 16
    else:
        header = 6
        sys_at = pos + 3
        msg_id = buf[pos + 5]
    crc_end = pos + header + payload_len
    extra = _CRC_EXTRA.get(msg_id)
    known = extra is not None
    if known:
        crc = x25crc(bytes(buf[pos + 1:crc_end]))
        crc.accumulate(bytes((extra,)))  # type: ignore[arg-type]
        if crc.crc != buf[crc_end] | buf[crc_end + 1] << 8:
            return None
    return Frame(bytes(buf[pos:pos + frame_len]), msg_id, buf[sys_at], buf[sys_at + 1],
                 2 if v2 else 1, known)


def decoder() -> Any:
    """A pymavlink parser for the frames `FrameSplitter` cuts (``decoder().decode(bytes)``)."""
    parser = apm.MAVLink(None)
    parser.robust_parsing = True
    return parser
