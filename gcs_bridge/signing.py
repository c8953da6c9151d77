"""MAVLink 2 message signing: the key file, signature checks and the per-link policy.

The key file holds a passphrase (one line); the 32-byte secret is SHA-256 of it, which is how
MAVProxy (`signing setup PASSPHRASE`) and QGroundControl turn a passphrase into a key, so the
same file configures the aircraft and every ground station. A file holding exactly 64 hex
digits is taken as the raw key instead.

Signatures are checked here rather than by pymavlink: pymavlink records a stream's timestamp
before it checks the signature, so one forged packet with a far-future timestamp would lock
the real ground station out until that time. Here a timestamp only counts once the signature
is good, and the table of streams is bounded.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import re
import secrets
import stat
import struct
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from companion.core.config import ConfigError
from gcs_bridge.dialect import mavlink

log = logging.getLogger(__name__)

SIGNATURE_LEN = 13  # link id (1) + timestamp (6) + signature (6)
EPOCH_2015_US = 1_420_070_400 * 1_000_000
NEW_STREAM_WINDOW = 60 * 100_000  # one minute, in the 10 us units of signing timestamps
MAX_STREAMS = 256
_HEX_KEY = re.compile(r"^[0-9a-fA-F]{64}$")

# Messages that change the aircraft. Everything else only asks for information or changes what
# this one link sends, and may be accepted unsigned on a link that allows unsigned reads.
# FILE_TRANSFER_PROTOCOL counts as a read here: the FTP server itself refuses every writing
# operation unless the request was signed with the key (see gcs_bridge/services/ftp.py).
WRITE_MESSAGES: frozenset[int] = frozenset({
    mavlink.MAVLINK_MSG_ID_LOG_ERASE,
    mavlink.MAVLINK_MSG_ID_SERIAL_CONTROL,  # the console can restart threads and set parameters
    mavlink.MAVLINK_MSG_ID_PARAM_SET,
    mavlink.MAVLINK_MSG_ID_PARAM_EXT_SET,
    mavlink.MAVLINK_MSG_ID_COMMAND_LONG,
    mavlink.MAVLINK_MSG_ID_COMMAND_INT,
    mavlink.MAVLINK_MSG_ID_SET_MODE,
    mavlink.MAVLINK_MSG_ID_SETUP_SIGNING,
    mavlink.MAVLINK_MSG_ID_MISSION_COUNT,
    mavlink.MAVLINK_MSG_ID_MISSION_ITEM,
    mavlink.MAVLINK_MSG_ID_MISSION_ITEM_INT,
    mavlink.MAVLINK_MSG_ID_MISSION_CLEAR_ALL,
    mavlink.MAVLINK_MSG_ID_MISSION_SET_CURRENT,
    mavlink.MAVLINK_MSG_ID_MISSION_WRITE_PARTIAL_LIST,
    mavlink.MAVLINK_MSG_ID_SET_HOME_POSITION,
    mavlink.MAVLINK_MSG_ID_SET_GPS_GLOBAL_ORIGIN,
    mavlink.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET,
    mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED,
    mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT,
    mavlink.MAVLINK_MSG_ID_MANUAL_CONTROL,
    mavlink.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE,
    mavlink.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET,
})

#: Commands that only ask for information: they change nothing on the aircraft.
READ_ONLY_COMMANDS: frozenset[int] = frozenset({
    mavlink.MAV_CMD_REQUEST_MESSAGE,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION,
    mavlink.MAV_CMD_GET_HOME_POSITION,
    mavlink.MAV_CMD_GET_MESSAGE_INTERVAL,
})


class KeyFileError(ConfigError):
    """A key file that cannot be used; the message names the file and the problem."""


def signing_timestamp(realtime_ns: int) -> int:
    """MAVLink signing time: 10 us units since 2015-01-01 00:00 UTC."""
    return max(0, (realtime_ns // 1000 - EPOCH_2015_US) // 10)


def key_from_text(text: str) -> bytes:
    """The 32-byte secret for a passphrase, or for 64 hex digits taken as the raw key."""
    t = text.strip()
    if _HEX_KEY.match(t):
        return bytes.fromhex(t)
    return hashlib.sha256(t.encode("utf-8")).digest()


def read_key_file(path: Path) -> tuple[bytes, str]:
    """Return (secret, passphrase) from a key file; raises KeyFileError naming the file."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise KeyFileError(f"{p}: cannot read signing key file: {exc.strerror or exc}") from None
    if len(raw) > 4096:
        raise KeyFileError(f"{p}: not a signing key file ({len(raw)} bytes, expected one line)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise KeyFileError(f"{p}: not UTF-8 text (byte {exc.start})") from None
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) != 1:
        raise KeyFileError(f"{p}: expected exactly one passphrase line, found {len(lines)}")
    passphrase = lines[0]
    if len(passphrase) < 8 and not _HEX_KEY.match(passphrase):
        raise KeyFileError(f"{p}: passphrase shorter than 8 characters")
    try:
        mode = p.stat().st_mode
    except OSError as exc:
        raise KeyFileError(f"{p}: cannot stat signing key file: {exc.strerror or exc}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        # Anyone who can read the key can sign frames the aircraft obeys: refuse to fly on it.
        raise KeyFileError(f"{p}: readable or writable by others (mode {stat.S_IMODE(mode):o}); "
                           f"run chmod 600 {p}")
    return key_from_text(passphrase), passphrase


def new_key_file(path: Path, *, force: bool = False) -> str:
    """Create a key file with a fresh random passphrase (mode 600); returns the passphrase."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    passphrase = secrets.token_urlsafe(24)
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if force else os.O_EXCL)
    try:
        fd = os.open(p, flags, 0o600)
    except FileExistsError:
        raise KeyFileError(f"{p}: exists already (use --force to replace it)") from None
    except OSError as exc:
        raise KeyFileError(f"{p}: cannot create: {exc.strerror or exc}") from None
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write("# MAVLink 2 signing passphrase (key = SHA-256 of this line)\n")
        fh.write(passphrase + "\n")
    os.chmod(p, 0o600)
    return passphrase


class SignatureChecker:
    """Checks signed MAVLink 2 frames against one key, with replay protection per stream."""

    def __init__(self, key: bytes, now_timestamp: Callable[[], int]) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key is 32 bytes")
        self._key = key
        self._now = now_timestamp
        self._streams: OrderedDict[tuple[int, int, int], int] = OrderedDict()

    def check(self, frame: bytes | bytearray) -> str | None:
        """None when the frame is signed, authentic and fresh; otherwise why not."""
        if len(frame) < 10 + 2 + SIGNATURE_LEN or frame[0] != 0xFD or not frame[2] & 0x01:
            return "unsigned"
        sig = bytes(frame[-6:])
        expected = hashlib.sha256(self._key + bytes(frame[:-6])).digest()[:6]
        if not hmac.compare_digest(sig, expected):
            return "bad signature"
        link_id = frame[-13]
        tlow, thigh = struct.unpack("<IH", bytes(frame[-12:-6]))
        timestamp = tlow | (thigh << 32)
        key = (link_id, frame[5], frame[6])
        last = self._streams.get(key)
        if last is not None:
            if timestamp <= last:
                return "replayed (old timestamp)"
        elif timestamp + NEW_STREAM_WINDOW < self._now():
            return "stale timestamp"
        self._streams[key] = timestamp
        self._streams.move_to_end(key)
        while len(self._streams) > MAX_STREAMS:
            self._streams.popitem(last=False)
        return None

    def streams(self) -> dict[tuple[int, int, int], int]:
        """A copy of the stream table, (link id, system id, component id) -> last timestamp.

        For inspection (tests, the flood benchmark): only frames signed with the key ever
        create or advance an entry, so forged traffic must leave this table unchanged.
        """
        return dict(self._streams)


@dataclass(frozen=True)
class LinkPolicy:
    """What one link accepts. `key` None: signing off on this link, everything accepted."""

    key: bytes | None
    unsigned_reads: bool = True

    @property
    def signing(self) -> bool:
        return self.key is not None


def is_write(msg_id: int, command: int | None = None) -> bool:
    """True for messages that change the aircraft (and must be signed when signing is on)."""
    if msg_id in (mavlink.MAVLINK_MSG_ID_COMMAND_LONG, mavlink.MAVLINK_MSG_ID_COMMAND_INT):
        return command not in READ_ONLY_COMMANDS
    return msg_id in WRITE_MESSAGES
